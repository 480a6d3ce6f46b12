"""A ray-cast world of textured rectangles: floor (optionally with a ramp), walls and boxes.

Every surface is a bounded plane ``p = origin + u * axis_u + v * axis_v`` with
``0 <= u <= length_u`` and ``0 <= v <= length_v``. Rendering casts one ray per pixel
against all planes at once (vectorised), picks the nearest hit, and samples a procedural
texture through a mip-mapped atlas (trilinear) so distant surfaces do not alias.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from ..camera import CameraModel, DistortionModel
from . import exact
from .exact import inv_T

TEXEL_M = 0.005  # texture resolution: one texel is 5 mm
TEX_SIZE = 1024  # texels per tile side (a tile is 5.12 m)
MIP_LEVELS = 5
MIP_PAD = 2


@dataclass
class Plane:
    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    length_u: float
    length_v: float
    tex_offset: tuple[float, float] = (0.0, 0.0)
    brightness: float = 1.0
    contrast: float = 1.0  # texture contrast around mid-grey (0: a uniform, featureless surface)
    # A specular-like sheen: this much brightness added at grazing view angles, (1 - cos)^3 (a polished floor).
    gloss: float = 0.0

    @cached_property
    def normal(self) -> np.ndarray:  # (the axes are fixed once a plane is made)
        n = np.cross(self.axis_u, self.axis_v)
        return n / exact.norm(n)

    def corners(self) -> np.ndarray:
        o, a, b = self.origin, self.axis_u * self.length_u, self.axis_v * self.length_v
        return np.stack([o, o + a, o + a + b, o + b])


def textured_rect(origin, axis_u, axis_v, lu, lv, rng: np.random.Generator, brightness: float, facing=None) -> Plane:
    """A textured rectangle; with ``facing`` its visible side (normal) points towards that point."""
    origin = np.asarray(origin, float)
    au = np.asarray(axis_u, float)
    av = np.asarray(axis_v, float)
    if facing is not None:
        n = np.cross(au, av)
        if exact.dot(np.asarray(facing, float) - origin, n) < 0:
            origin = origin + au / exact.norm(au) * lu
            au = -au
    return Plane(
        np.asarray(origin, float),
        au / exact.norm(au),
        av / exact.norm(av),
        float(lu),
        float(lv),
        (float(rng.uniform(0, 10)), float(rng.uniform(0, 10))),
        brightness,
    )


def box_planes(center_xy, size_xyz, rng: np.random.Generator, z0: float = 0.0) -> list[Plane]:
    """Four vertical faces and the top of an axis-aligned box standing on z=z0."""
    cx, cy = center_xy
    sx, sy, sz = size_xyz
    x0, x1, y0, y1 = cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2
    b = rng.uniform(0.7, 1.0)
    return [
        textured_rect([x0, y0, z0], [1, 0, 0], [0, 0, 1], sx, sz, rng, b, facing=[cx, y0 - 50, z0]),
        textured_rect([x1, y1, z0], [-1, 0, 0], [0, 0, 1], sx, sz, rng, b, facing=[cx, y1 + 50, z0]),
        textured_rect([x0, y1, z0], [0, -1, 0], [0, 0, 1], sy, sz, rng, b * 0.9, facing=[x0 - 50, cy, z0]),
        textured_rect([x1, y0, z0], [0, 1, 0], [0, 0, 1], sy, sz, rng, b * 0.9, facing=[x1 + 50, cy, z0]),
        textured_rect([x0, y0, z0 + sz], [1, 0, 0], [0, 1, 0], sx, sy, rng, b * 1.05, facing=[cx, cy, z0 + sz + 50]),
    ]


def oriented_box_planes(center_xy, yaw: float, size_xyz, rng: np.random.Generator, z0: float = 0.0,
                        brightness: float | None = None) -> list[Plane]:
    """Four vertical faces and the top of a box standing on z=z0, its x side along heading ``yaw``."""
    c = np.append(np.asarray(center_xy, float), z0)
    sx, sy, sz = size_xyz
    ex = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    ey = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    ez = np.array([0.0, 0.0, 1.0])
    b = float(rng.uniform(0.7, 1.0)) if brightness is None else brightness
    lo = c - ex * sx / 2 - ey * sy / 2
    hi = c + ex * sx / 2 + ey * sy / 2
    return [
        textured_rect(lo, ex, ez, sx, sz, rng, b, facing=c - 50 * ey),
        textured_rect(hi, -ex, ez, sx, sz, rng, b, facing=c + 50 * ey),
        textured_rect(lo + ey * sy, -ey, ez, sy, sz, rng, b * 0.9, facing=c - 50 * ex),
        textured_rect(hi - ey * sy, ey, ez, sy, sz, rng, b * 0.9, facing=c + 50 * ex),
        textured_rect(lo + ez * sz, ex, ey, sx, sy, rng, b * 1.05, facing=c + (sz + 50) * ez),
    ]


@dataclass
class MovingBox:
    start_xy: np.ndarray
    end_xy: np.ndarray
    size_xyz: tuple[float, float, float]
    period_s: float
    seed: int

    def planes_at(self, t: float) -> list[Plane]:
        s = 0.5 - 0.5 * np.cos(2 * np.pi * t / self.period_s)
        c = (1 - s) * np.asarray(self.start_xy) + s * np.asarray(self.end_xy)
        return box_planes(c, self.size_xyz, np.random.default_rng(self.seed))


@dataclass
class Ramp:
    """Floor height h(x): 0 before x0, rising linearly to ``height`` at x1, flat after."""

    x0: float
    x1: float
    height: float

    def height_at(self, x: np.ndarray | float) -> np.ndarray | float:
        s = np.clip((np.asarray(x, float) - self.x0) / (self.x1 - self.x0), 0.0, 1.0)
        return s * self.height

    def slope_at(self, x: float) -> float:
        return self.height / (self.x1 - self.x0) if self.x0 < x < self.x1 else 0.0


@dataclass
class Scene:
    planes: list[Plane]
    moving: list[MovingBox] = field(default_factory=list)
    ramp: Ramp | None = None
    texture_seed: int = 0

    def ground_height(self, x: float, y: float) -> float:
        return float(self.ramp.height_at(x)) if self.ramp is not None else 0.0

    def ground_normal(self, x: float, y: float) -> np.ndarray:
        if self.ramp is None:
            return np.array([0.0, 0.0, 1.0])
        s = self.ramp.slope_at(x)
        n = np.array([-s, 0.0, 1.0])
        return n / exact.norm(n)

    def planes_at(self, t: float) -> list[Plane]:
        out = list(self.planes)
        for m in self.moving:
            out.extend(m.planes_at(t))
        return out


def make_room_scene(
    seed: int,
    half_x: float = 9.0,
    half_y: float = 9.0,
    wall_h: float = 3.0,
    obstacles: list[tuple[float, float, float, float, float]] | None = None,
    ramp: Ramp | None = None,
    moving: list[MovingBox] | None = None,
    floor_contrast: float = 1.0,
) -> Scene:
    """A walled room with textured floor and box obstacles ``(x, y, sx, sy, sz)``; ``floor_contrast`` 0
    makes the floor (and ramp) featureless."""
    rng = np.random.default_rng(seed)
    planes: list[Plane] = []
    if ramp is None:
        planes.append(textured_rect([-half_x, -half_y, 0], [1, 0, 0], [0, 1, 0], 2 * half_x, 2 * half_y, rng, 1.0, facing=[0, 0, 100]))
    else:
        h = ramp.height
        L = np.hypot(ramp.x1 - ramp.x0, h)
        planes.append(textured_rect([-half_x, -half_y, 0], [1, 0, 0], [0, 1, 0], ramp.x0 + half_x, 2 * half_y, rng, 1.0, facing=[0, 0, 100]))
        planes.append(
            textured_rect([ramp.x0, -half_y, 0], [ramp.x1 - ramp.x0, 0, h], [0, 1, 0], L, 2 * half_y, rng, 0.95, facing=[ramp.x0, 0, 100])
        )
        planes.append(textured_rect([ramp.x1, -half_y, h], [1, 0, 0], [0, 1, 0], half_x - ramp.x1, 2 * half_y, rng, 1.0, facing=[0, 0, 100]))
    for fp in planes:
        fp.contrast = floor_contrast
    wb = 0.85
    planes.append(textured_rect([-half_x, -half_y, -1], [1, 0, 0], [0, 0, 1], 2 * half_x, wall_h + 1, rng, wb, facing=[0, 0, 1]))
    planes.append(textured_rect([half_x, half_y, -1], [-1, 0, 0], [0, 0, 1], 2 * half_x, wall_h + 1, rng, wb, facing=[0, 0, 1]))
    planes.append(textured_rect([-half_x, half_y, -1], [0, -1, 0], [0, 0, 1], 2 * half_y, wall_h + 1, rng, wb * 0.9, facing=[0, 0, 1]))
    planes.append(textured_rect([half_x, -half_y, -1], [0, 1, 0], [0, 0, 1], 2 * half_y, wall_h + 1, rng, wb * 0.9, facing=[0, 0, 1]))
    for ox, oy, sx, sy, sz in obstacles or []:
        z0 = float(ramp.height_at(ox)) if ramp is not None else 0.0
        planes.extend(box_planes((ox, oy), (sx, sy, sz), rng, z0=z0))
    return Scene(planes, moving or [], ramp, texture_seed=seed)


# ---------------------------------------------------------------------------- textures


def make_texture(seed: int, size: int = TEX_SIZE) -> np.ndarray:
    """A tileable grey texture with blobs, patches and edges at several scales (float32, 0..1)."""
    rng = np.random.default_rng(seed)
    tex = np.zeros((size, size), np.float32)
    for cells, amp in ((8, 0.3), (32, 0.25), (128, 0.2), (384, 0.12)):
        small = rng.random((cells, cells)).astype(np.float32)
        tiled = np.tile(small, (3, 3))
        big = cv2.resize(tiled, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)[size : 2 * size, size : 2 * size]
        tex += amp * big
    # Hard-edged patches (corners for the tracker), drawn with wrap-around.
    canvas = np.zeros((3 * size, 3 * size), np.float32)
    mask = np.zeros_like(canvas)
    for _ in range(900):
        x, y = rng.integers(size, 2 * size, 2)
        w, h = rng.integers(6, 40, 2)
        val = float(rng.uniform(-0.5, 0.5))
        if rng.random() < 0.5:
            cv2.rectangle(canvas, (int(x), int(y)), (int(x + w), int(y + h)), val, -1)
        else:
            cv2.circle(canvas, (int(x), int(y)), int(w // 2 + 3), val, -1)
        cv2.rectangle(mask, (int(x), int(y)), (int(x + w), int(y + h)), 1.0, -1)
    folded = np.zeros((size, size), np.float32)
    for i in range(3):
        for j in range(3):
            folded += canvas[i * size : (i + 1) * size, j * size : (j + 1) * size]
    tex = tex + folded
    pad = 8
    blurred = cv2.GaussianBlur(cv2.copyMakeBorder(tex, pad, pad, pad, pad, cv2.BORDER_WRAP), (0, 0), 0.8)
    tex = np.asarray(blurred, np.float32)[pad:-pad, pad:-pad]
    tex -= tex.min()
    tex /= max(float(tex.max()), 1e-6)
    return 0.12 + 0.76 * tex


def wrap_mod(x: np.ndarray, size: np.ndarray, inv_size: np.ndarray | None) -> np.ndarray:
    """``np.mod(x, size)`` for positive sizes; exact (the same bits) and faster when sizes are powers of two.

    With ``size = 2^k`` the quotient ``x * (1 / size)``, its floor and ``floor * size`` are exact in
    float32, and so is the difference (the remainder is a multiple of x's ulp below ``size``): both
    ways give the one rounding of the same exact remainder, +0.0 included.
    """
    if inv_size is None:
        return np.mod(x, size)
    return x - np.floor(x * inv_size) * size


class MipAtlas:
    """Mip levels of a tileable texture laid side by side, each padded by wrapping."""

    def __init__(self, texture: np.ndarray, levels: int = MIP_LEVELS):
        self.levels = []
        img = texture.astype(np.float32)
        x = 0
        blocks = []
        for lvl in range(levels):
            padded = cv2.copyMakeBorder(img, MIP_PAD, MIP_PAD, MIP_PAD, MIP_PAD, cv2.BORDER_WRAP)
            self.levels.append((x + MIP_PAD, MIP_PAD, img.shape[1]))  # (x offset, y offset, size)
            blocks.append(padded)
            x += padded.shape[1]
            if lvl + 1 < levels:
                wrapped = cv2.copyMakeBorder(img, 8, 8, 8, 8, cv2.BORDER_WRAP)
                img = np.asarray(cv2.pyrDown(wrapped), np.float32)[4:-4, 4:-4]
        h = blocks[0].shape[0]
        self.atlas = np.zeros((h, x), np.float32)
        xo = 0
        for b in blocks:
            self.atlas[: b.shape[0], xo : xo + b.shape[1]] = b
            xo += b.shape[1]
        self.offsets = np.array([lv[0] for lv in self.levels], np.float32)
        self.sizes = np.array([lv[2] for lv in self.levels], np.float32)
        # Per-level lookup tables: 1 / 2^l (exact in float32) and, where every level's size is a power
        # of two, 1 / size, so the wrap below is exact arithmetic (the same bits as np.mod, faster).
        self.scales = np.float32(1.0) / (np.float32(2.0) ** np.arange(levels, dtype=np.float32))
        pow2 = all(int(n) & (int(n) - 1) == 0 for n in self.sizes)
        self.inv_sizes = (np.float32(1.0) / self.sizes) if pow2 else None

    def sample(self, s: np.ndarray, t: np.ndarray, level: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Trilinear sample at texel coordinates (s, t) of level 0 and fractional mip ``level``."""
        lv0 = np.floor(level).astype(np.int32)
        frac = (level - lv0).astype(np.float32)
        lv1 = np.minimum(lv0 + 1, len(self.levels) - 1)
        out = np.zeros(shape, np.float32)
        for lv, wgt in ((lv0, 1.0 - frac), (lv1, frac)):
            size = self.sizes[lv]
            scale = self.scales[lv]
            # pyrDown keeps the even texels, so texel j of level l sits at level-0 index 2^l j:
            # a continuous level-0 coordinate s (texel centres at i + 0.5) is index (s - 0.5) / 2^l.
            inv_size = None if self.inv_sizes is None else self.inv_sizes[lv]
            ss = wrap_mod((s - 0.5) * scale, size, inv_size)
            tt = wrap_mod((t - 0.5) * scale, size, inv_size)
            mx = (ss + self.offsets[lv]).astype(np.float32).reshape(shape)
            my = (tt + MIP_PAD).astype(np.float32).reshape(shape)
            val = cv2.remap(self.atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            out += val * wgt.reshape(shape)
        return out


def raycast(planes: list[Plane], origin: np.ndarray, dirs: np.ndarray, near: float = 0.05):
    """Nearest hit of rays ``origin + t * dirs`` with the planes.

    Returns ``t`` (inf where nothing is hit), the plane index, and the plane coordinates (u, v).
    ``dirs`` need not be unit vectors; ``t`` is in units of ``dirs``.
    """
    N = dirs.shape[0]
    dirs32 = dirs.astype(np.float32, copy=False)
    normals = np.stack([p.normal for p in planes]).astype(np.float32)
    origins = np.stack([p.origin for p in planes]).astype(np.float32)
    au = np.stack([p.axis_u for p in planes]).astype(np.float32)
    av = np.stack([p.axis_v for p in planes]).astype(np.float32)
    lu = np.array([p.length_u for p in planes], np.float32)
    lv = np.array([p.length_v for p in planes], np.float32)
    o = origin.astype(np.float32)
    num = exact.rowwise_dot(origins - o, normals)  # (P,)
    # Cull planes that face away from the camera (the camera sits on their back side).
    front = num < 0
    idx_keep = np.nonzero(front)[0]
    if idx_keep.size == 0:
        return (np.full(N, np.inf, np.float32), np.zeros(N, np.int32), np.zeros(N, np.float32), np.zeros(N, np.float32))
    M = np.concatenate([normals[idx_keep], au[idx_keep], av[idx_keep]], axis=0).T  # (3, 3K)
    prod = exact.matmul(dirs32, M)  # (N, 3K)
    K = idx_keep.size
    dn, da, db = prod[:, :K], prod[:, K : 2 * K], prod[:, 2 * K :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num[idx_keep][None, :] / dn
    rel_u = exact.rowwise_dot(o - origins[idx_keep], au[idx_keep])
    rel_v = exact.rowwise_dot(o - origins[idx_keep], av[idx_keep])
    u = rel_u[None, :] + t * da
    v = rel_v[None, :] + t * db
    ok = (t > near) & (u >= 0) & (u <= lu[idx_keep][None, :]) & (v >= 0) & (v <= lv[idx_keep][None, :])
    t = np.where(ok, t, np.inf)
    best = np.argmin(t, axis=1)
    rows = np.arange(N)
    t_best = t[rows, best]
    return t_best, idx_keep[best].astype(np.int32), u[rows, best], v[rows, best]


@dataclass
class _Buffers:
    """Per-pixel state of the nearest surface so far."""

    tbuf: np.ndarray  # ray parameter of the nearest hit
    s_tex: np.ndarray
    t_tex: np.ndarray
    cosb: np.ndarray
    bright: np.ndarray
    contrast: np.ndarray
    gloss: np.ndarray | None  # only when some plane is glossy

    @classmethod
    def empty(cls, shape: tuple[int, int], glossy: bool) -> _Buffers:
        return cls(np.full(shape, np.inf, np.float32), np.zeros(shape, np.float32), np.zeros(shape, np.float32),
                   np.ones(shape, np.float32), np.zeros(shape, np.float32), np.ones(shape, np.float32),
                   np.zeros(shape, np.float32) if glossy else None)


class Renderer:
    """Renders grey images of a scene for a fixed camera model (lens distortion included).

    Each pixel casts the undistorted ray through its centre. Pinhole and radtan cameras use
    rays with z = 1; the equidistant (fisheye) model uses unit bearing vectors, so a lens
    wider than 180 degrees sees beside and behind its own lens plane.

    Planes are rasterised one at a time over the pixel block their outline can cover, with
    a depth buffer; the cost follows the covered area, not planes x pixels.
    """

    def __init__(self, scene: Scene, camera: CameraModel, seed: int = 0):
        self.scene = scene
        self.camera = camera
        H, W = camera.height, camera.width
        self.shape = (H, W)
        self.wide = camera.distortion_model is DistortionModel.EQUIDISTANT
        grid = camera.pixel_grid()
        bearings = camera.pixel_bearings()
        # Pixels where the lens model cannot be inverted (a distortion polynomial that folds back
        # before the image corner) see nothing, like the dark rim outside a fisheye's image circle.
        with np.errstate(invalid="ignore", divide="ignore"):
            back = camera.project(bearings)
        self.valid = (np.linalg.norm(back - grid, axis=1) < 0.01).reshape(H, W)
        bearings[~self.valid.ravel()] = (0.0, 0.0, 1.0)
        rays = bearings if self.wide else bearings / bearings[:, 2:3]
        self.rays_cam = rays.astype(np.float32).reshape(H, W, 3)
        self.ray_len = np.sqrt((self.rays_cam * self.rays_cam).sum(axis=2))
        self.theta_max = float(np.arccos(np.clip(bearings[:, 2].min(), -1.0, 1.0)))  # widest ray of any pixel
        xn, yn = self.rays_cam[..., 0], self.rays_cam[..., 1]
        # Conservative normalised-coordinate range of each pixel column and row (z = 1 rays).
        self.col_x = (xn.min(axis=0), xn.max(axis=0))
        self.row_y = (yn.min(axis=1), yn.max(axis=1))
        self.atlas = MipAtlas(make_texture(scene.texture_seed))
        self.base_footprint = np.float32(1.0 / camera.fx)
        self._corners: np.ndarray | None = None
        self.x_min, self.x_max = float(self.col_x[0].min()), float(self.col_x[1].max())
        self.y_min, self.y_max = float(self.row_y[0].min()), float(self.row_y[1].max())

    def _outline(self, plane: Plane, T_cam_world: np.ndarray, per_edge: int) -> np.ndarray:
        """Points densely sampled along the plane's border, in the camera frame."""
        c = plane.corners()
        edge = np.linspace(0.0, 1.0, per_edge + 1)[:-1, None]
        outline = np.concatenate([c[i] + edge * (c[(i + 1) % 4] - c[i]) for i in range(4)])
        return exact.matmul(outline, T_cam_world[:3, :3].T) + T_cam_world[:3, 3]

    def _block(self, plane: Plane, T_cam_world: np.ndarray, near: float):
        """Row and column slices of the image the plane can cover, or None."""
        return self._block_wide(plane, T_cam_world) if self.wide else self._block_pinhole(plane, T_cam_world, near)

    def _block_pinhole(self, plane: Plane, T_cam_world: np.ndarray, near: float):
        # Clip the outline against z >= near, then bound it in normalised coordinates.
        pc = self._outline(plane, T_cam_world, 8)
        z = pc[:, 2]
        if np.all(z < near):
            return None
        nxt = np.roll(pc, -1, axis=0)
        front, crosses = z >= near, (z >= near) != (nxt[:, 2] >= near)
        a, b = pc[crosses], nxt[crosses]
        s = (near - a[:, 2]) / (b[:, 2] - a[:, 2])
        q = np.concatenate([pc[front], a + s[:, None] * (b - a)])
        xn = q[:, 0] / q[:, 2]
        yn = q[:, 1] / q[:, 2]
        x0, x1, y0, y1 = xn.min(), xn.max(), yn.min(), yn.max()
        cols = np.nonzero((self.col_x[1] >= x0) & (self.col_x[0] <= x1))[0]
        rows = np.nonzero((self.row_y[1] >= y0) & (self.row_y[0] <= y1))[0]
        if cols.size == 0 or rows.size == 0:
            return None
        return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)

    def _wide_outline_pixels(self, pc: np.ndarray) -> np.ndarray:
        """Fisheye pixels of camera-frame points, continued monotonically past the widest pixel ray.

        Within the image's field of view this is the lens projection; beyond it the radius
        keeps growing with the off-axis angle, so a lens polynomial that folds back outside
        its calibrated range cannot pull points from behind the camera into the image.
        """
        cam = self.camera
        r = np.hypot(pc[:, 0], pc[:, 1])
        theta = np.arctan2(r, pc[:, 2])
        inside = theta <= self.theta_max
        theta_d = np.where(inside, cam._equidistant_theta_d(np.minimum(theta, self.theta_max)),
                           cam._equidistant_theta_d(np.array(self.theta_max)) + (theta - self.theta_max))
        scale = theta_d / np.maximum(r, 1e-15)
        return np.stack([cam.fx * pc[:, 0] * scale + cam.cx, cam.fy * pc[:, 1] * scale + cam.cy], axis=1)

    def _block_wide(self, plane: Plane, T_cam_world: np.ndarray):
        # The fisheye maps every direction but the one straight behind the lens continuously
        # into the image plane, so a rectangle's image lies inside its projected outline.
        # A rectangle that holds that backward direction wraps around the image: take all.
        H, W = self.shape
        full = slice(0, H), slice(0, W)
        pc = self._outline(plane, T_cam_world, 48)
        T_world_cam = inv_T(T_cam_world)
        back_hit, _, _, _ = raycast([plane], T_world_cam[:3, 3], -T_world_cam[:3, 2][None, :], near=0.0)
        if np.isfinite(back_hit[0]):
            return full
        uv = self._wide_outline_pixels(pc)
        margin = 2.0
        c0, c1 = np.floor(uv[:, 0].min() - margin), np.ceil(uv[:, 0].max() + margin)
        r0, r1 = np.floor(uv[:, 1].min() - margin), np.ceil(uv[:, 1].max() + margin)
        if c1 < 0 or r1 < 0 or c0 > W - 1 or r0 > H - 1:
            return None
        return slice(int(max(r0, 0)), int(min(r1, H - 1)) + 1), slice(int(max(c0, 0)), int(min(c1, W - 1)) + 1)

    def _static_corners(self) -> np.ndarray:
        """Corners (P, 4, 3) of the scene's fixed planes, computed once."""
        if self._corners is None or len(self._corners) != len(self.scene.planes):
            self._corners = np.stack([p.corners() for p in self.scene.planes]) if self.scene.planes else np.zeros((0, 4, 3))
        return self._corners

    def _in_front(self, planes: list[Plane], T_cam_world: np.ndarray, near: float) -> list[Plane]:
        """The planes not wholly behind the camera's near plane (a pinhole lens sees none of those).

        A cheap, vectorised test before the per-plane work: it only drops planes that the block test
        would drop anyway, so images do not change; streets with hundreds of planes stay fast.
        """
        if self.wide:
            return planes
        n_static = len(self.scene.planes)
        corners = self._static_corners()
        if len(planes) > n_static:
            corners = np.concatenate([corners, np.stack([p.corners() for p in planes[n_static:]])])
        pc = exact.matmul(corners, T_cam_world[:3, :3].T) + T_cam_world[:3, 3]  # (P, 4, 3) corners in the camera frame
        x, y, z = pc[..., 0], pc[..., 1], pc[..., 2]
        keep = (z >= near).any(axis=1)
        # ... nor wholly beyond one side of the view frustum (a convex set: then no pixel ray meets them)
        keep &= (x <= self.x_max * z).any(axis=1) & (x >= self.x_min * z).any(axis=1)
        keep &= (y <= self.y_max * z).any(axis=1) & (y >= self.y_min * z).any(axis=1)
        # ... nor clearly seen from their back (the exact test stays in _raster)
        normals = np.stack([p.normal for p in planes])
        origins = corners[:, 0]
        keep &= exact.rowwise_dot(origins - inv_T(T_cam_world)[:3, 3], normals) < 1e-6
        return [p for p, k in zip(planes, keep) if k]

    def _raster(self, p: Plane, T_world_cam: np.ndarray, T_cam_world: np.ndarray, near: float, buf: _Buffers) -> None:
        """Draw one plane into the buffers where it is nearer than what they hold."""
        R = T_world_cam[:3, :3].astype(np.float32)
        cam_o = T_world_cam[:3, 3]
        n = p.normal
        num = exact.dot(p.origin - cam_o, n)
        if num >= 0:  # camera behind the plane's visible side
            return
        blk = self._block(p, T_cam_world, near)
        if blk is None:
            return
        rs, cs = blk
        rays = self.rays_cam[rs, cs]  # (h, w, 3) camera frame
        # Plane quantities expressed in the camera frame: one dot product per pixel each.
        n_c = exact.matmul(R.T, n.astype(np.float32))
        a_c = exact.matmul(R.T, p.axis_u.astype(np.float32))
        b_c = exact.matmul(R.T, p.axis_v.astype(np.float32))
        dn = exact.matmul(rays, n_c)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ray = np.float32(num) / dn
        rel = (cam_o - p.origin)
        u = np.float32(exact.dot(rel, p.axis_u)) + t_ray * exact.matmul(rays, a_c)
        v = np.float32(exact.dot(rel, p.axis_v)) + t_ray * exact.matmul(rays, b_c)
        tb = buf.tbuf[rs, cs]
        ok = (t_ray > near) & (t_ray < tb) & (u >= 0) & (u <= p.length_u) & (v >= 0) & (v <= p.length_v)
        if not ok.any():
            return
        tb[ok] = t_ray[ok]
        buf.s_tex[rs, cs][ok] = (u[ok] + p.tex_offset[0]) / TEXEL_M
        buf.t_tex[rs, cs][ok] = (v[ok] + p.tex_offset[1]) / TEXEL_M
        buf.cosb[rs, cs][ok] = np.abs(dn[ok]) / self.ray_len[rs, cs][ok]  # ray_len: the same norm, computed once
        buf.bright[rs, cs][ok] = p.brightness
        buf.contrast[rs, cs][ok] = p.contrast
        if buf.gloss is not None:
            buf.gloss[rs, cs][ok] = p.gloss

    def render(self, T_world_cam: np.ndarray, t: float, gain: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Image (float32 0..1) and range seen from ``T_world_cam``.

        The range is the distance (m) from the camera centre to the surface along each pixel's
        ray (inf where nothing is hit); it is defined for every lens, fisheye included.
        """
        planes = self.scene.planes_at(t)
        near = 0.05
        T_cam_world = inv_T(T_world_cam)
        buf = _Buffers.empty(self.shape, glossy=any(p.gloss > 0 for p in planes))
        for p in self._in_front(planes, T_cam_world, near):
            self._raster(p, T_world_cam, T_cam_world, near, buf)
        buf.tbuf[~self.valid] = np.inf
        hit = np.isfinite(buf.tbuf)
        range_m = buf.tbuf * self.ray_len  # ray parameter -> metres along the ray
        footprint = np.where(hit, range_m, 1.0) * self.base_footprint / np.sqrt(np.maximum(buf.cosb, 0.05))
        level = np.clip(exact.log2(np.maximum(footprint / TEXEL_M, 1e-6)), 0.0, MIP_LEVELS - 1.001).astype(np.float32)
        img = self.atlas.sample(buf.s_tex.ravel(), buf.t_tex.ravel(), level.ravel(), self.shape)
        img = 0.5 + (img - 0.5) * buf.contrast
        img *= buf.bright
        if buf.gloss is not None:  # sheen towards grazing angles: view-dependent, like a polished floor
            grazing = 1.0 - buf.cosb
            img += buf.gloss * (grazing * grazing * grazing)
        img[~hit] = 0.05
        img *= gain
        return img, range_m

    def surface_points(self, T_world_cam: np.ndarray, uv: np.ndarray, t: float) -> np.ndarray:
        """World points (N,3) seen at pixels ``uv`` (nan where no surface)."""
        dirs = exact.matmul(self.camera.unproject(uv), T_world_cam[:3, :3].T)  # unit bearings: any lens
        depth, _, _, _ = raycast(self.scene.planes_at(t), T_world_cam[:3, 3], dirs)
        p = T_world_cam[:3, 3][None, :] + depth[:, None] * dirs
        p[~np.isfinite(depth)] = np.nan
        return p
