"""The floor measured by region: the length of a keyframe step from the floor's pixels (``ground.road_region``).

Corner-based floor landmarks need corners on the floor that live three keyframes; the asphalt in front of a car
(or a plain warehouse floor) has few. The floor's pixels tell the step's length anyway: between keyframes k-1 and
k, a floor point seen by camera k-1 at ray ``x`` is seen by camera k at ``(R + s t_dir n^T) x`` (the
plane-induced homography in normalised coordinates: ``X_k = R X_{k-1} + t``, the floor ``n . X = h`` in camera
k-1 with ``n`` its unit normal pointing down and ``h`` the camera's height above it, ``s = |t| / h``). With the
rotation ``R`` and the direction ``t_dir`` from the window's estimate, only ``s`` is unknown: the ``s`` whose warp of
the floor region of image k-1 into image k correlates best (zero-mean normalised cross-correlation, so a change of
exposure does not matter) gives the step's metric length ``s h`` (Song & Chandraker, CVPR 2014, reduced to the one
unknown the estimate leaves; ``scripts/road_homography_study.py`` measured the building block on the KITTI
excerpts). The back end ties it to the keyframes' base poses with a range factor (``range_factor``).

What the measurement assumes, and so what its sigma says: the region is floor (a car parked in it, a kerb beside
it: the correlation drops, the robust loss and the correlation threshold take it out), and the floor is a plane
whose height under the camera is the known one. Its attitude against the camera is not assumed: the region's rays
meet the floor at grazing angles, so a pitch error ``da`` moves ``s`` by about ``da / tan(depression)`` (9% a degree
with a car's camera looking 6-10 m ahead), and a real road's slope in front of the car differs from the slope under
its wheels by a degree and more (KITTI 01's first 50 frames: 1.2-1.7 deg by stereo). So each step searches the
floor's pitch about the camera's x axis too (``pitch_search_deg`` either side of the assumed normal), jointly with
the length on one grid: the two trade along a ridge (a longer step on a floor pitched further down), which only the
change of the floor's image motion from the region's near rows to its far ones separates, hence a region reaching
``pitch_far_heights`` (10) camera heights ahead. The assumed normal is the floor's learnt one (``FloorAttitude``: a mount
pitched against ``T_base_cam``) when known, else the set-up's (the base's z axis); on a base rocking on its suspension,
the window's mean of it seen from the step's first keyframe (``RoadRegion.level_floor``: the keyframe's rocking
applied; the pitches are still pooled against the mount's normal). A step's sigma is ``sigma_fraction`` of its
length. Until the pool can be tested (5 searches) a step's pitch is untested: with wheels the step is neither tied nor
checked against them, but measured again on the pooled pitch once that is tested (``RoadRegion.after_update``);
without, it is tied, its sigma widened by ``untested_pitch_deg``. Pixels whose gradient lies across their
flow (a lane line along the motion) tell no length and may be left out (``min_gradient_alignment``). Masked pixels (``frontend`` masks: a bonnet, the robot's own body) are left out of the region in both images.
The images are smoothed (``blur_px``) and, optionally, contrast-normalised (``normalise_px``: a bright lane line then
weighs no more than the asphalt) before the region is sampled; image k is read between its pixels bilinearly, or
bicubically (``interpolation``), which biases a warp's scale less (docs/scale_suite.md, "How the region samples its
images").

What the length rides on: the estimate's rotation between the two cameras. A longer step and the newer camera
tilted down (about its x axis) both move the floor's pixels down the image, the first more on the near rows than the
far ones, which is all that tells them apart: on a car's camera 0.1 deg of tilt is 2-6% of the length, and at ground
truth's poses the rendered straight streets' steps scatter by 0.4% where at the run's estimate they scatter by 4%
(``scripts/road_region_pose_study.py``). With ``tilt_ridge_deg``, on a base rocking on its suspension, the length is
measured again with the camera tilted either way (``_tilt_slope``) and the step is tied along that ridge
(``ridge_factor``): the window's tilt, refined after the step was measured, picks its length.

Where the length is searched: around the estimate's, +42% / -30% (``COARSE_SPAN``); with wheels that is the calibrated
wheels' step, and a step beyond it a slipping wheel. Without, a monocular run's scale may have drifted further while
the floor was out of reach: the grid moves out while its best length lies at its edge (``monocular_search_shifts``).
A monocular run's first step has no estimate of its length at all: with ``metric_start`` it is searched on one grid
over 0.03-3 camera heights (``RoadRegion.first_baseline``).

The measurement (``measure_step``, ``RoadRegionCue``: which images, which step) is numpy and OpenCV, tested on its own
(``tests/test_road_region.py``); ``RoadRegion`` is the smoother's side (when to measure, when its range factor may go
in), and ``range_factor`` and ``ridge_factor`` its GTSAM factors.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BackendConfig, RegionInterpolation, RoadRegionConfig
from ..geometry import rot_x, rot_y
from .floor import MIN_ROCKING_KEYFRAMES
from .ground import attitude_jitter_deg, level_up

# The search (``_search``): a coarse grid of COARSE_STEPS lengths over +-COARSE_SPAN (log) around the estimate's step,
# a parabola through the best one and its neighbours, then REFINE_ROUNDS rounds of the direction's sideways angle
# and the length on grids of FINE_STEPS (the length over 3 FINE_SPAN, the angle over search_direction_deg), each
# round on a third of the last span.
COARSE_STEPS = 29
COARSE_SPAN = 0.35
FINE_STEPS = 9
FINE_SPAN = 0.03
REFINE_ROUNDS = 3  # rounds of the alternating search (direction, length), each on a third of the span
# With the floor's pitch searched: REFINE_ROUNDS + 1 rounds of the direction and a FINE_STEPS x FINE_STEPS grid of the
# length and the pitch, the length's span at least PITCH_LENGTH_SPAN (log units) per radian of the pitch's span (the
# ridge along which they trade: about 9% of length a degree on a car's camera).
PITCH_LENGTH_SPAN = 12.0
# The ridge of length and camera k's tilt (``_tilt_slope``): each side's length searched over this many log units per
# radian of tilt either side of the step's (the ridge's slope on a car's camera: about 20 a radian).
RIDGE_SPAN_PER_RAD = 60.0
REMAP_COLS = 16384  # cv2.remap's map is folded into rows of this many points (it takes fewer than SHRT_MAX columns)
MEMO_REGIONS = 8  # floor rays a cue keeps (one set per assumed floor)
BLUR_SIGMA_PX = 1.0  # the images' smoothing before sampling by default (``road_region.blur_px``)
INTERPOLATION = {RegionInterpolation.LINEAR: cv2.INTER_LINEAR, RegionInterpolation.CUBIC: cv2.INTER_CUBIC}


@dataclass(frozen=True)
class RoadStep:
    """One keyframe step measured by the floor's region: its length between the cameras and between the bases."""

    keyframe: int  # the step k-1 -> k
    camera_m: float  # the cameras' distance, s h
    base_m: float  # the base origins' distance (what the range factor ties)
    estimate_camera_m: float  # the estimate's camera distance when measured
    correlation: float  # at the best scale
    n_pixels: int
    pitch_deg: float  # the floor's pitch the step found against the assumed normal (camera x axis)
    sigma_fraction: float  # its range factor's sigma as a share of its length (RoadRegionCue.step_sigma_fraction)
    tilt_slope: float = 0.0  # d log(camera_m) / d(camera k's tilt, rad) along the ridge; 0: a plain range factor
    # the estimate's camera rotation when measured (what the tilt is against); not compared (an array)
    R_cam0_cam1: np.ndarray | None = field(default=None, compare=False)


@dataclass(frozen=True)
class StepFit:
    """``measure_step``'s answer: the cameras' distance, the alignment's correlation at it, the region pixels it used
    and the floor's pitch it found (about the camera's x axis, against the assumed normal; 0 when not searched)."""

    camera_m: float
    correlation: float
    n_pixels: int
    pitch_deg: float = 0.0
    tilt_slope: float = 0.0  # d log(length) / d(camera k's tilt, rad) along the ridge (``tilt_ridge_deg``; 0: none)


def floor_in_camera(T_base_cam: np.ndarray, n_base: np.ndarray, floor_offset: float) -> tuple[np.ndarray, float]:
    """The floor ``n_base . p = floor_offset`` (base frame, ``n_base`` up) as ``n . X = h`` in the camera frame,
    ``n`` pointing down: returns ``(n, h)``."""
    R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
    n_cam = -(R_bc.T @ n_base)
    h = float(n_base @ t_bc - floor_offset)
    return n_cam / np.linalg.norm(n_cam), h


def pixel_grid(camera: CameraModel, step_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ``step_px``-th pixel of the image (as measured) and its unit ray: computed once per camera."""
    s = step_px
    v, u = np.mgrid[s // 2:camera.height:s, s // 2:camera.width:s]
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    return uv, camera.unproject(uv.astype(float))


def floor_rays(grid: tuple[np.ndarray, np.ndarray], n_cam: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of ``grid`` (``pixel_grid``) whose rays meet the floor ``n . X = h`` ahead, and those rays scaled
    to meet it: ``(uv (N, 2) int, X (N, 3))``; ``region_rays`` takes its region from them."""
    uv, rays = grid
    ny = rays @ n_cam
    ok = ny > 1e-6
    lam = np.where(ok, h / np.where(ok, ny, 1.0), 0.0)
    X = rays * lam[:, None]
    ok &= X[:, 2] > 0
    return uv[ok], X[ok]


def region_rays(grid: tuple[np.ndarray, np.ndarray], n_cam: np.ndarray, h: float, cfg: RoadRegionConfig,
                floor: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of ``grid`` (``pixel_grid``) whose rays meet the floor within the region ahead (``near_heights``
    to ``far_heights`` camera heights along the optical axis, ``half_width_heights`` beside it), and those rays
    scaled to meet the floor: ``(uv (N, 2) int, X (N, 3))``, X on the plane ``n . X = h``. ``floor``: ``floor_rays``
    of the same grid and plane, when the caller has them."""
    uv, X = floor if floor is not None else floor_rays(grid, n_cam, h)
    ok = (X[:, 2] >= cfg.near_heights * h) & (X[:, 2] <= cfg.far_heights * h)
    ok &= np.abs(X[:, 0]) <= cfg.half_width_heights * h
    uv, X = uv[ok], X[ok]
    if len(uv) > cfg.max_pixels:  # an even subsample
        keep = np.linspace(0, len(uv) - 1, cfg.max_pixels).round().astype(int)
        uv, X = uv[keep], X[keep]
    return uv, X


def smoothed(image: np.ndarray, sigma_px: float = BLUR_SIGMA_PX, normalise_px: float = 0.0,
             normalise_floor: float = 2.0) -> np.ndarray:
    """The float image the measurement samples: smoothed by a Gaussian of ``sigma_px`` (0: as it is), then, with
    ``normalise_px``, its local contrast normalised: ``(I - mean) / (std + normalise_floor)`` over Gaussian
    neighbourhoods of that sigma (the correlation is then not ruled by a few high-contrast pixels)."""
    img: np.ndarray = image.astype(np.float32)
    if sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigma_px)
    if normalise_px <= 0:
        return img
    d = img - cv2.GaussianBlur(img, (0, 0), normalise_px)
    return d / (np.sqrt(cv2.GaussianBlur(d * d, (0, 0), normalise_px)) + np.float32(normalise_floor))


class _Warp:
    """The correlation of the floor region of image k-1 with image k warped by the floor's homography, per s."""

    def __init__(self, camera: CameraModel, img0: np.ndarray, img1: np.ndarray, uv0: np.ndarray, X0: np.ndarray,
                 R: np.ndarray, t_dir: np.ndarray, n_cam: np.ndarray, h: float, min_pixels: int,
                 mask1: np.ndarray | None = None, interpolation: RegionInterpolation = RegionInterpolation.LINEAR):
        self.camera, self.img1, self.mask1 = camera, img1, mask1
        self.interpolation = INTERPOLATION[interpolation]
        self.pinhole = not camera.has_distortion
        self.a = img0[uv0[:, 1], uv0[:, 0]].astype(np.float32)
        a = self.a.astype(np.float64)
        self.a_sums = np.stack([a, a * a], axis=1)  # (N, 2): a weight row times it gives sum a, sum a^2
        self.b_sums = np.stack([np.ones_like(a), a], axis=1)  # (N, 2): a sample row times it gives sum b, sum a b
        self.X0, self.R, self.h, self.n_cam = X0, R, h, n_cam  # the region's points on the assumed floor, camera k-1
        self.RX0 = X0 @ R.T  # (R X) for each floor point, camera k
        self.RX = self.RX0.astype(np.float32)
        self.nX = (X0 @ n_cam).astype(np.float32)  # n . X for each point (h on the floor)
        self.set_direction(t_dir)
        self.n_last = 0
        self.min_pixels = min_pixels
        # samples whose interpolation reads only image k's own pixels (bicubic: one more on the far sides)
        far = 2.0 if interpolation is RegionInterpolation.LINEAR else 3.0
        self.bounds = (1.0, camera.width - far, 1.0, camera.height - far)

    def set_rotation(self, R: np.ndarray) -> None:
        """The rotation of camera k against camera k-1 the warp takes (``X_k = R X_{k-1} + t``)."""
        self.R = R
        self.RX0 = self.X0 @ R.T
        self.RX = self.RX0.astype(np.float32)

    def set_direction(self, t_dir: np.ndarray) -> None:
        self.tn = np.outer(self.nX, t_dir).astype(np.float32)  # t_dir (n . X) per point: s times it is the translation

    def on_plane(self, n: np.ndarray, t_dir: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(R X, t_dir (n . X))`` (N, 3) each for the region's rays met on the floor ``n . X = h`` instead of the
        assumed one: the points of camera k at length s are the first plus s times the second."""
        RX, tn = self.on_planes(n[None], t_dir[None])
        return RX[0], tn[0]

    def on_planes(self, ns: np.ndarray, t_dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``on_plane`` for K floors' normals ``ns`` (K, 3) and directions ``t_dirs`` (K, 3) at once: (K, N, 3) each."""
        d = self.X0 @ ns.T  # (N, K)
        f = self.h / np.where(d > 1e-9, d, 1e-9)  # each ray's point on that floor is f times its point on the assumed
        RX = (self.RX0[None] * f.T[:, :, None]).astype(np.float32)
        tn = ((d * f).T[:, :, None] * t_dirs[:, None, :]).astype(np.float32)
        return RX, tn

    def pixels(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        return self._project(self.RX + np.float32(s) * self.tn)  # R X + s t_dir (n . X), and n . X = h: R X + t

    def _project(self, Xk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (..., 2) of the points ``Xk`` (..., 3) in camera k, and which lie in front (-1 where not)."""
        front = Xk[..., 2] > 1e-6
        if self.pinhole:
            c = self.camera
            z = np.where(front, Xk[..., 2], np.float32(1.0))
            uv = np.stack([c.fx * Xk[..., 0] / z + c.cx, c.fy * Xk[..., 1] / z + c.cy], axis=-1).astype(np.float32)
            uv[~front] = -1.0
            return uv, front
        uv = np.full(Xk.shape[:-1] + (2,), -1.0, np.float32)
        uv[front] = self.camera.project(Xk[front].astype(np.float64))
        return uv, front

    def _project_xyz(self, X: np.ndarray, Y: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pixels' columns and rows (S, N) float32 each of the points given by their coordinates (S, N) each in
        camera k, and which lie in front (``_project``, without the points' (S, N, 3) array for a pinhole camera)."""
        if not self.pinhole:
            uv, front = self._project(np.stack([X, Y, Z], axis=-1))
            return np.ascontiguousarray(uv[..., 0]), np.ascontiguousarray(uv[..., 1]), front
        c = self.camera
        front = Z > 1e-6
        z = np.where(front, Z, np.float32(1.0))
        u = (np.float32(c.fx) * X / z + np.float32(c.cx)).astype(np.float32)
        v = (np.float32(c.fy) * Y / z + np.float32(c.cy)).astype(np.float32)
        return u, v, front

    def correlation(self, s: float) -> tuple[float, int]:
        return self.correlations(np.array([s]), self.tn[None])[0], self.n_last

    def correlations(self, ss: np.ndarray, tns: np.ndarray) -> list[float]:
        """``correlation`` of the lengths ``ss`` (S,), each with its direction's ``t_dir (n . X)`` (``tns``: (S, N, 3)
        or (1, N, 3) for one direction), in one pass: the same numbers as one call per length, with the numpy and
        OpenCV work done once for all S (``n_last``: the last one's pixels)."""
        s = ss.astype(np.float32)[:, None]
        return self._correlate(*self._project_xyz(*(self.RX[None, :, i] + s * tns[:, :, i] for i in range(3))))

    def correlations_at(self, RX: np.ndarray, tn: np.ndarray, ss) -> list[float]:
        """The correlation of the candidate warps whose points in camera k are ``RX[p] + ss[l] tn[p]``, for each of P
        floors (``on_planes``: (P, N, 3) each; one floor's ``RX`` (1, N, 3) goes with P directions' ``tn``) and L
        lengths ``ss``: P x L candidates in that order (the floor's index the slower). Each coordinate is built on
        its own: the same float32 numbers as the points built whole, without their (P L, N, 3) array."""
        s = np.asarray(ss, np.float32)[None, :, None]
        n = RX.shape[1]
        X, Y, Z = ((RX[:, None, :, i] + s * tn[:, None, :, i]).reshape(-1, n) for i in range(3))
        return self._correlate(*self._project_xyz(X, Y, Z))

    def _correlate(self, u: np.ndarray, v: np.ndarray, front: np.ndarray) -> list[float]:
        """The correlation of each of S candidate warps, given as the pixels (S, N) of the region's points in image k
        and which lie in front of camera k.

        All S at once: every point is sampled (one outside image k or behind it at the image's corner), those
        outside, behind or on image k's mask with no weight, and each candidate's zero-mean normalised
        cross-correlation is taken over its own points by weighted sums (float64), so no candidate's points are
        gathered one by one."""
        u0, u1, v0, v1 = self.bounds
        inside = front & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)
        outside = ~inside
        np.copyto(u, np.float32(u0), where=outside)  # sampled, weighed 0
        np.copyto(v, np.float32(v0), where=outside)
        if self.mask1 is not None:  # samples landing on masked pixels of image k are no floor
            inside &= self.mask1[(v + 0.5).astype(int), (u + 0.5).astype(int)] != 0
        counts = inside.sum(axis=1)
        self.n_last = int(counts[-1])
        S, N = inside.shape
        if N < REMAP_COLS:
            b = cv2.remap(self.img1, u, v, self.interpolation).astype(np.float64)
        else:
            b = _remap(self.img1, np.stack([u.ravel(), v.ravel()], axis=1),
                       self.interpolation).reshape(S, N).astype(np.float64)
        b *= inside
        w = inside.astype(np.float64)
        n = np.maximum(counts, 1).astype(np.float64)
        sa, saa = (w @ self.a_sums).T  # the sums over each candidate's own points (float64: no cancellation)
        sb, sab = (b @ self.b_sums).T
        num = sab - sa * sb / n
        var_a = np.maximum(saa - sa * sa / n, 0.0)
        var_b = np.maximum(np.einsum("ij,ij->i", b, b) - sb * sb / n, 0.0)
        den = np.sqrt(var_a * var_b)
        ok = (counts >= self.min_pixels) & (den > 1e-9)
        return [float(num[i] / den[i]) if ok[i] else -1.0 for i in range(S)]

    def flow_px(self, s: float) -> float:
        """Median displacement of the region's pixels between s = 0 (rotation only) and s."""
        uv0, f0 = self.pixels(0.0)
        uv1, f1 = self.pixels(s)
        ok = f0 & f1
        return float(np.median(np.linalg.norm(uv1[ok] - uv0[ok], axis=1))) if ok.any() else 0.0


def _remap(img: np.ndarray, m: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """``img`` sampled (``interpolation``: OpenCV's) at the points ``m`` (M, 2): one ``cv2.remap``, its map folded into
    rows (remap takes at most SHRT_MAX columns); each point's value is its own, however the map is folded."""
    n = len(m)
    if n == 0:
        return np.zeros(0, np.float32)
    cols = min(n, REMAP_COLS)
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = m[:, 0], m[:, 1]
    return cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), interpolation).ravel()[:n]


def _parabola_peak(xs: np.ndarray, cs: np.ndarray, i: int) -> float:
    """The vertex of the parabola through the best grid point and its two neighbours (the grid point at an edge)."""
    if i == 0 or i == len(xs) - 1:
        return float(xs[i])
    c0, c1, c2 = cs[i - 1], cs[i], cs[i + 1]
    den = c0 - 2 * c1 + c2
    if den >= 0:
        return float(xs[i])
    off = 0.5 * (c0 - c2) / den
    return float(xs[i] + off * (xs[i + 1] - xs[i]))


def gradient_along_flow(img: np.ndarray, uv: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Each pixel's share of its image gradient along its flow: ``|g . f| / (|g| |f|)`` for the pixels ``uv`` (N, 2)
    int of ``img`` (central differences, clamped at the image's border) and their flows ``f`` (N, 2); 1 where the
    gradient or the flow is zero.

    A step's length (and the floor's pitch) moves the floor's pixels along their flow (the rays from the focus of
    expansion), so only the gradient's component along it tells them; a pixel whose gradient is across it (the
    flank of a lane line parallel to the motion) fits every length alike. Such pixels are not harmless: on the
    rendered straight streets, whose lane lines run along the region's sides, they pull the pitch search half a
    degree off at ground truth's motion and the length 4-6% long (docs/scale_suite.md, "Lane lines along the
    motion"). Direct methods select their pixels by the same argument (LSD-SLAM's gradient along the epipolar line).
    ``road_region.min_gradient_alignment`` keeps the pixels whose share is at least it."""
    hgt, wid = img.shape[:2]
    u, v = uv[:, 0], uv[:, 1]
    ul, ur = np.clip(u - 1, 0, wid - 1), np.clip(u + 1, 0, wid - 1)
    vu, vd = np.clip(v - 1, 0, hgt - 1), np.clip(v + 1, 0, hgt - 1)
    g = np.stack([img[v, ur].astype(np.float64) - img[v, ul], img[vd, u].astype(np.float64) - img[vu, u]], axis=1)
    f = np.asarray(flow, np.float64)
    dot = np.abs((g * f).sum(axis=1))
    norm = np.linalg.norm(g, axis=1) * np.linalg.norm(f, axis=1)
    return np.where(norm > 1e-12, dot / np.where(norm > 1e-12, norm, 1.0), 1.0)


def measure_step(camera: CameraModel, img0: np.ndarray, img1: np.ndarray, T_world_cam0: np.ndarray,
                 T_world_cam1: np.ndarray, n_cam: np.ndarray, h: float, cfg: RoadRegionConfig,
                 grid: tuple[np.ndarray, np.ndarray] | None = None,
                 masks: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
                 memo: dict | None = None, coarse_span: float = COARSE_SPAN) -> StepFit | None:
    """The camera step's metric length from the floor region (``img0``/``img1``: ``smoothed`` images of the two
    keyframes; the poses give the rotation and the direction; ``n_cam``, ``h``: the assumed floor in camera k-1).

    The estimate's direction is not exact, and a sideways error of it shifts the floor's pixels sideways by an
    amount that grows with the length: a road's lane lines make that costly, so a shorter step would win (10% on a
    curve for a direction 0.6 deg off). The direction's sideways angle is searched too (``search_direction_deg``),
    alternately with the length: it moves the pixels across the image, the length along their rays, so the two
    separate. The floor's pitch is searched with the length (``pitch_search_deg``; the module's docstring). Returns
    the fit, or None when the floor region does not measure it: too few pixels, too little motion of the floor in
    the image, the correlation below ``min_correlation``, or the length's peak at the edge of its search.
    ``memo``: the caller's store of ``floor_rays`` by assumed floor (they depend on nothing else with one ``grid``).
    With ``min_gradient_alignment``, the region's pixels whose gradient lies across their flow at the estimate's
    length are left out first (``gradient_along_flow``)."""
    T_c1_c0 = np.linalg.inv(T_world_cam1) @ T_world_cam0
    R, t = T_c1_c0[:3, :3], T_c1_c0[:3, 3]
    d_est = float(np.linalg.norm(t))
    if d_est < 1e-6 or h <= 0:
        return None
    grid = grid if grid is not None else pixel_grid(camera, cfg.step_px)
    key = (n_cam.tobytes(), h)
    if memo is not None and key in memo:
        floor = memo[key]
    else:
        floor = floor_rays(grid, n_cam, h)
        if memo is not None:
            if len(memo) >= MEMO_REGIONS:
                memo.clear()
            memo[key] = floor
    uv0, X0 = region_rays(grid, n_cam, h, cfg, floor)
    if masks[0] is not None:  # the pixels masked in image k-1 are no floor
        usable = masks[0][uv0[:, 1], uv0[:, 0]] > 0
        uv0, X0 = uv0[usable], X0[usable]
    if len(uv0) < cfg.min_pixels:
        return None
    t_dir = t / d_est
    s_est = d_est / h
    warp = _Warp(camera, img0, img1, uv0, X0, R, t_dir, n_cam, h, cfg.min_pixels, masks[1], cfg.interpolation)
    if cfg.min_gradient_alignment > 0:
        (uv_s, _), (uv_r, _) = warp.pixels(s_est), warp.pixels(0.0)
        keep = gradient_along_flow(img0, uv0, uv_s - uv_r) >= cfg.min_gradient_alignment
        if keep.sum() < cfg.min_pixels:
            return None
        uv0, X0 = uv0[keep], X0[keep]
        warp = _Warp(camera, img0, img1, uv0, X0, R, t_dir, n_cam, h, cfg.min_pixels, masks[1], cfg.interpolation)
    if warp.flow_px(s_est) < cfg.min_flow_px:
        return None
    if cfg.pitch_search_deg > 0:
        return _search_with_pitch(warp, t_dir, s_est, h, cfg, coarse_span)
    return _search(warp, t_dir, s_est, h, cfg, coarse_span)


def _coarse_lengths(correlations: Callable[[np.ndarray], np.ndarray], log_s: float, shifts: int,
                    span: float = COARSE_SPAN) -> tuple[float, float, bool]:
    """The search's coarse grid of log lengths over +-``span`` around ``log_s``, COARSE_STEPS of them over
    +-COARSE_SPAN (wider spans at the same spacing): the best one's log length (a parabola through it and its
    neighbours), its correlation, and whether it lies inside the grid. While it lies at an edge, the grid is moved
    out to that edge and searched again, up to ``shifts`` times (``monocular_search_shifts``: a monocular run's
    estimate may be off its step by more than the grid's span)."""
    steps = 2 * round(span / COARSE_SPAN * (COARSE_STEPS - 1) / 2) + 1
    centre = log_s
    for _ in range(shifts + 1):
        xs = centre + np.linspace(-span, span, steps)
        c = np.asarray(correlations(xs))
        i = int(np.argmax(c))
        inside = 0 < i < steps - 1
        if inside:
            break
        centre = float(xs[i])
    return _parabola_peak(xs, c, i), float(c[i]), inside


def _search(warp: _Warp, t_dir: np.ndarray, s_est: float, h: float, cfg: RoadRegionConfig,
            coarse_span: float = COARSE_SPAN) -> StepFit | None:
    """``measure_step``'s search on the assumed floor: a coarse grid of the length around the estimate's, then rounds
    of the direction's sideways angle and the length, each on a third of the last span."""
    # p = [log s, sideways turn of the direction]
    p = np.array([np.log(s_est), 0.0])

    beta = [0.0]  # the sideways turn the warp's direction has now

    def turn(b: float) -> None:
        if b != beta[0]:
            warp.set_direction(rot_y(b) @ t_dir)  # about the camera's y axis
            beta[0] = b

    def corr(q: np.ndarray) -> float:
        turn(float(q[1]))
        return warp.correlation(float(np.exp(q[0])))[0]

    def line(axis: int, span: float, steps: int) -> tuple[float, bool]:
        xs = p[axis] + np.linspace(-span, span, steps)
        if axis == 0:  # the lengths, at the direction p has
            turn(float(p[1]))
            cs = warp.correlations(np.array([np.exp(x) for x in xs]), warp.tn[None])
        else:  # the directions, at the length p has
            tns = np.stack([np.outer(warp.nX, rot_y(float(x)) @ t_dir).astype(np.float32) for x in xs])
            cs = warp.correlations(np.full(steps, float(np.exp(p[0]))), tns)
        c = np.asarray(cs)
        i = int(np.argmax(c))
        p[axis] = _parabola_peak(xs, c, i)
        return float(c[i]), 0 < i < steps - 1

    turn(float(p[1]))
    p[0], c, inside = _coarse_lengths(
        lambda xs: np.asarray(warp.correlations(np.array([np.exp(x) for x in xs]), warp.tn[None])), float(p[0]),
        cfg.monocular_search_shifts, coarse_span)
    if not inside or c < cfg.min_correlation:
        return None
    span_dir, span_s = float(np.radians(cfg.search_direction_deg)), 3 * FINE_SPAN
    for _ in range(REFINE_ROUNDS if span_dir > 0 else 1):
        if span_dir > 0:
            line(1, span_dir, FINE_STEPS)
            span_dir /= 3.0
        c, inside = line(0, span_s, FINE_STEPS)
        span_s /= 3.0
    c_best = corr(p)
    if not inside or c_best < cfg.min_correlation:
        return None
    n_pixels = warp.n_last
    slope = _tilt_slope(warp, rot_y(float(p[1])) @ t_dir, float(p[0]), cfg) if cfg.tilt_ridge_deg > 0 else 0.0
    return StepFit(float(np.exp(p[0])) * h, c_best, n_pixels, tilt_slope=slope)


def _tilt_slope(warp: _Warp, t_dir: np.ndarray, log_s: float, cfg: RoadRegionConfig) -> float:
    """How the step's length trades with camera k's tilt about its x axis (rad): the best length with camera k
    tilted by ``tilt_ridge_deg`` up and down (its centre kept), the slope of log length between the two (0 where a
    side has no peak inside either round of its search, or correlates below ``min_correlation`` there). A longer step and a camera tilted down both move the floor's pixels down
    the image (the first more on the near rows than the far ones, which is all that tells them apart), so the
    region measures the length well only at a given tilt: on a car's camera 0.15 deg of tilt is 3% of length."""
    R0, d = warp.R, float(np.radians(cfg.tilt_ridge_deg))
    ends = []
    for w in (-d, d):
        dR = rot_x(w)
        warp.set_rotation(dR @ R0)
        warp.set_direction(dR @ t_dir)
        x0, span, ok = log_s, RIDGE_SPAN_PER_RAD * d, True
        for _ in range(2):
            xs = x0 + np.linspace(-span, span, 2 * FINE_STEPS + 1)
            c = np.asarray(warp.correlations(np.exp(xs), warp.tn[None]))
            i = int(np.argmax(c))
            ok = ok and 0 < i < len(xs) - 1 and bool(c[i] >= cfg.min_correlation)
            x0, span = _parabola_peak(xs, c, i), span / 6.0
        ends.append(x0 if ok else None)
    warp.set_rotation(R0)
    warp.set_direction(t_dir)
    if ends[0] is None or ends[1] is None:
        return 0.0
    return float((ends[1] - ends[0]) / (2.0 * d))


def _search_with_pitch(warp: _Warp, t_dir: np.ndarray, s_est: float, h: float, cfg: RoadRegionConfig,
                       coarse_span: float = COARSE_SPAN) -> StepFit | None:
    """``measure_step``'s search with the floor's pitch: a coarse grid of the length on the assumed floor, then rounds
    of the direction's sideways angle (a line) and of the length and the pitch together (a grid: they trade along a
    ridge), each on a third of the last span (the pitch's once its peak lies inside its grid); the length's peak must
    lie inside its last grid, as on the assumed floor."""
    p = np.array([np.log(s_est), 0.0, 0.0])  # log s, the direction's sideways turn, the floor's pitch (rad)

    def plane(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return warp.on_plane(rot_x(float(q[2])) @ warp.n_cam, rot_y(float(q[1])) @ t_dir)

    def pick(xs: np.ndarray, c: np.ndarray, axis: int) -> tuple[float, bool]:
        i = int(np.argmax(c))
        p[axis] = _parabola_peak(xs, c, i)
        return float(c[i]), 0 < i < len(xs) - 1

    def directions(span: float, steps: int) -> None:
        xs = p[1] + np.linspace(-span, span, steps)
        n = rot_x(float(p[2])) @ warp.n_cam
        RX, tn = warp.on_planes(n[None], np.stack([rot_y(float(x)) @ t_dir for x in xs]))  # one floor, its points once
        pick(xs, np.asarray(warp.correlations_at(RX, tn, [np.exp(p[0])])), 1)

    def lengths_and_pitches(span_s: float, span_t: float, steps: int) -> tuple[float, bool, bool]:
        ls = p[0] + np.linspace(-span_s, span_s, steps)
        ts = p[2] + np.linspace(-span_t, span_t, steps)
        d = rot_y(float(p[1])) @ t_dir
        RX, tn = warp.on_planes(np.stack([rot_x(float(t)) @ warp.n_cam for t in ts]), np.tile(d, (steps, 1)))
        c = np.asarray(warp.correlations_at(RX, tn, np.exp(ls))).reshape(steps, steps)  # (pitch, length)
        it, il = (int(i) for i in np.unravel_index(int(np.argmax(c)), c.shape))
        p[0] = _parabola_peak(ls, c[it], il)
        p[2] = _parabola_peak(ts, c[:, il], it)
        return float(c[it, il]), 0 < il < steps - 1, 0 < it < steps - 1

    RX0, tn0 = plane(p)
    p[0], c, inside = _coarse_lengths(lambda xs: np.asarray(warp.correlations_at(RX0[None], tn0[None], np.exp(xs))),
                                      float(p[0]), cfg.monocular_search_shifts, coarse_span)
    if not inside or c < cfg.min_correlation:
        return None
    span_dir, span_t = float(np.radians(cfg.search_direction_deg)), float(np.radians(cfg.pitch_search_deg))
    span_s = max(3 * FINE_SPAN, PITCH_LENGTH_SPAN * span_t)
    for _ in range(REFINE_ROUNDS + 1):
        if span_dir > 0:
            directions(span_dir, FINE_STEPS)
            span_dir /= 3.0
        c, inside, pitch_inside = lengths_and_pitches(span_s, span_t, FINE_STEPS)
        span_s /= 3.0
        if pitch_inside:  # a pitch at the grid's edge keeps its span: the next grid, centred there, goes on
            span_t /= 3.0
    RX, tn = plane(p)
    c_best = warp.correlations_at(RX[None], tn[None], [np.exp(p[0])])[0]
    if not inside or c_best < cfg.min_correlation:
        return None
    return StepFit(float(np.exp(p[0])) * h, c_best, warp.n_last, float(np.degrees(p[2])))


def base_distance(T_base_cam: np.ndarray, T_world_cam0: np.ndarray, T_world_cam1: np.ndarray,
                  camera_m: float) -> float:
    """The base origins' distance of a step whose cameras are ``camera_m`` apart, in the direction and with the
    rotation of the estimate's step (the camera sits off the base origin: on a turn the two paths differ)."""
    T_c0_c1 = np.linalg.inv(T_world_cam0) @ T_world_cam1
    d = float(np.linalg.norm(T_c0_c1[:3, 3]))
    T = T_c0_c1.copy()
    T[:3, 3] *= camera_m / max(d, 1e-12)
    T_b0_b1 = T_base_cam @ T @ np.linalg.inv(T_base_cam)
    return float(np.linalg.norm(T_b0_b1[:3, 3]))


def _ridge_error(T_base_cam: np.ndarray, log_camera_m: float, slope: float, R_cam0_cam1: np.ndarray,
                 this, values, H: list | None) -> np.ndarray:
    """Residual of a step's length on the ridge it trades along with camera k's tilt: ``log |t| - log camera_m -
    slope * tilt``, ``t`` the cameras' step and ``tilt`` camera k's turn about its x axis against the rotation the
    step was measured at (``R_cam0_cam1``), both at the poses' values."""
    import gtsam

    k0, k1 = this.keys()
    H1 = np.zeros((6, 6), order="F")
    H2 = np.zeros((6, 6), order="F")
    D = values.atPose3(k0).between(values.atPose3(k1), H1, H2)
    Dm = D.matrix()
    R_D, t_D = Dm[:3, :3], Dm[:3, 3]
    R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
    t_c = R_bc.T @ (R_D @ t_bc + t_D - t_bc)  # camera k's centre in camera k-1's frame
    L = float(np.linalg.norm(t_c))
    E = R_bc.T @ R_D.T @ R_bc @ R_cam0_cam1  # camera k's rotation now against the one measured at
    H_log = np.zeros((3, 3), order="F")
    tilt = float(gtsam.Rot3.Logmap(gtsam.Rot3(E), H_log)[0])
    err = np.array([np.log(max(L, 1e-12)) - log_camera_m - slope * tilt])
    if H is not None:
        g = t_c / max(L * L, 1e-24)  # d log L / d t_c
        # D's rotation turned by w turns camera k by R_bc^T w: E -> Exp(-R_bc^T w) E = E Exp(-E^T R_bc^T w)
        d_tilt = -(H_log[0] @ E.T @ R_bc.T)
        J = np.zeros((1, 6))
        u = g @ R_bc.T @ R_D  # d log L / d(D's translation) (GTSAM's Pose3 tangent: t' = t + R v)
        J[0, :3] = np.cross(t_bc, u) - slope * d_tilt  # D's rotation (R Exp(w) t_bc: u . (w x t_bc)) and the tilt
        J[0, 3:] = u
        H[0] = J @ H1
        H[1] = J @ H2
    return err


def ridge_factor(key0: int, key1: int, step: RoadStep, T_base_cam: np.ndarray, robust_kind, robust_k: float):
    """The step's length tied to the two base poses along the ridge it trades on with camera k's tilt
    (``road_region.tilt_ridge_deg``): the region tells the length at a tilt, and the window's tilt (vision's,
    refined after the step was measured) picks the length on it. Sigma ``sigma_fraction`` of the length (log units)."""
    import gtsam

    from .factors import robust

    assert step.R_cam0_cam1 is not None
    noise = robust(gtsam.noiseModel.Isotropic.Sigma(1, step.sigma_fraction), robust_kind, robust_k)
    return gtsam.CustomFactor(noise, [key0, key1], partial(_ridge_error, np.asarray(T_base_cam, float),
                                                          float(np.log(step.camera_m)), float(step.tilt_slope),
                                                          np.asarray(step.R_cam0_cam1, float)))


def range_factor(key0: int, key1: int, base_m: float, sigma_m: float, robust_kind, robust_k: float):
    """The step's length as a range factor between the two base poses (GTSAM's native ``RangeFactorPose3``)."""
    import gtsam

    from .factors import robust

    noise = robust(gtsam.noiseModel.Isotropic.Sigma(1, sigma_m), robust_kind, robust_k)
    return gtsam.RangeFactorPose3(key0, key1, float(base_m), noise)


MIN_PITCH_SEARCHES = 5  # the pooled pitch is tested only once this many searches found one
# Keyframe images a cue keeps: the newest step's two, and those of the steps measured on a pitch not yet tested, which
# are measured again once it is (a step whose images are gone by then is not)
KEPT_IMAGES = 2 * MIN_PITCH_SEARCHES
# A monocular run's first step (``RoadRegion.first_baseline``): its length is unknown, so the coarse grid spans the
# lengths FIRST_STEP_HEIGHTS camera heights (a robot's 1.5 cm keyframe step under a camera 0.5 m up to 5 m under a
# car's camera 1.65 m up: a 2 m step at 10 Hz is 1.2), at the search's usual spacing (185 lengths)
FIRST_STEP_HEIGHTS = (0.03, 3.0)


def pooled_pitch(pitches: list[float], sigmas: float, systematic_deg: float = 0.0) -> float:
    """The floor's pitch against the assumed one that the steps' searches tell together: their median, when it lies
    ``sigmas`` standard errors from 0 with at least MIN_PITCH_SEARCHES of them; else 0, the assumed floor (one
    search's pitch is loose along its ridge with the length: a camera at its set-up's pitch keeps the set-up's).

    The median's standard error has two parts. Its own, 1.2533 x 1.4826 x MAD / sqrt(n), from the searches'
    spread, shrinks with their number. ``systematic_deg`` does not: what biases every search alike (the floor's
    texture, the images' smoothing, a lane line at the region's side) moves their median and not their spread, so
    n searches tell the pitch no better than it (docs/scale_suite.md, "The pitch searches' shared error")."""
    p = np.asarray(pitches, float)
    if len(p) < MIN_PITCH_SEARCHES:
        return 0.0
    med = float(np.median(p))
    se = 1.2533 * 1.4826 * float(np.median(np.abs(p - med))) / math.sqrt(len(p))
    return med if abs(med) > sigmas * math.hypot(se, systematic_deg) else 0.0


class RoadRegionCue:
    """The measurement's state between keyframes: the newest keyframes' smoothed images (``keep_image``), the pool
    of pitch searches, and each step measured from them once the window has estimated it (``measure``); which steps
    are tied, and when, is ``RoadRegion``'s."""

    def __init__(self, camera: CameraModel, cfg: RoadRegionConfig, T_base_cam: np.ndarray):
        self.camera, self.cfg, self.T_base_cam = camera, cfg, T_base_cam
        self.grid = pixel_grid(camera, cfg.step_px)
        self._rays: dict = {}  # measure_step's memo of region rays (for self.grid)
        # (keyframe, smoothed image, mask) of the newest keyframes: the step to the newest, and the steps measured on
        # an untested pitch, which are measured again once it is tested (``RoadRegion.after_update``)
        self._images: deque[tuple[int, np.ndarray, np.ndarray | None]] = deque(maxlen=KEPT_IMAGES)
        # The floor's pitch the last pitch_window searches found (at every step until there are that many, then at
        # every pitch_every-th), against the assumed normal they were searched from
        self.pitches: deque[float] = deque(maxlen=max(1, cfg.pitch_window))
        self.n_searches = 0  # pitch searches made (for the record and the tests)
        self._pitch_from: np.ndarray | None = None
        self._steps_since_search = 0
        plain = cfg.model_copy(update={"tilt_ridge_deg": 0.0})  # no ridge: the length alone
        self._pitch_search = plain.model_copy(update={"far_heights": cfg.pitch_far_heights})  # the pitch's region
        self._on_pitch = plain.model_copy(update={"pitch_search_deg": 0.0})  # a step's length on the pooled pitch
        self._on_pitch_ridge = cfg.model_copy(update={"pitch_search_deg": 0.0})  # ... and its ridge with the tilt
        self._plain = plain

    def keep_image(self, k: int, image: np.ndarray | None, mask: np.ndarray | None = None) -> None:
        """Keyframe k's image (grey, as measured) and its usable pixels (0: masked; None: all); no image: the step
        to it is not measured (k < 0: the kept images are forgotten, a window reset)."""
        if k < 0:
            self._images.clear()
        elif image is not None:
            c = self.cfg
            self._images.append((k, smoothed(image, c.blur_px, c.normalise_px, c.normalise_floor), mask))

    def forget_before(self, k: int) -> None:
        """Keyframe k's image and newer are all a step still to be measured needs (no untested step waits)."""
        while self._images and self._images[0][0] < k:
            self._images.popleft()

    def first_step(self, image: np.ndarray | None, mask: np.ndarray | None, T_world_cam0: np.ndarray,
                   T_world_cam1: np.ndarray, n_base: np.ndarray, floor_offset: float) -> StepFit | None:
        """The camera step from keyframe 0 (its image kept) to the image ``image`` of keyframe 1, whose camera pose
        ``T_world_cam1`` has the two views' rotation and direction at any baseline: a monocular run's first step, its
        coarse grid over FIRST_STEP_HEIGHTS (with the floor's pitch when ``pitch_search_deg``). Nothing is kept or
        pooled. None: no floor region measures it."""
        img0 = self._kept(0)
        if img0 is None or image is None:
            return None
        c = self.cfg
        img1 = smoothed(image, c.blur_px, c.normalise_px, c.normalise_floor)
        n_cam, h = floor_in_camera(self.T_base_cam, n_base, floor_offset)
        search = (self._pitch_search if c.pitch_search_deg > 0 else self._plain).model_copy(
            update={"monocular_search_shifts": 0})
        lo, hi = FIRST_STEP_HEIGHTS
        c0, c1 = T_world_cam0[:3, 3], T_world_cam1[:3, 3]
        T_mid = T_world_cam1.copy()  # the grid's centre: the geometric mean of its lengths
        T_mid[:3, 3] = c0 + (c1 - c0) * (math.sqrt(lo * hi) * h / max(float(np.linalg.norm(c1 - c0)), 1e-12))
        return measure_step(self.camera, img0[1], img1, T_world_cam0, T_mid, n_cam, h, search, self.grid,
                            (img0[2], mask), self._rays, coarse_span=0.5 * math.log(hi / lo))

    def _kept(self, k: int) -> tuple[int, np.ndarray, np.ndarray | None] | None:
        return next((f for f in reversed(self._images) if f[0] == k), None)

    def measure(self, k: int, T_world_base0: np.ndarray, T_world_base1: np.ndarray, n_base: np.ndarray,
                floor_offset: float, pool_normal: np.ndarray | None = None, search: bool = True,
                ridge: bool = False) -> RoadStep | None:
        """The step k-1 -> k from the floor region, at the estimate's poses (after keyframe k's update), if both
        images are kept. ``n_base``, ``floor_offset``: the floor in keyframe k-1's base frame. ``pool_normal``: the
        floor's normal in the base frame the pitches are pooled against (default ``n_base``; a rocking base's
        levelled floor moves ``n_base`` at every step, not the pitch the searches find). ``search`` false: the
        length on the pooled pitch alone, the pool untouched (a step measured again). ``ridge``: the length's trade
        with camera k's tilt measured too (``tilt_ridge_deg``; ``RoadStep.tilt_slope``, ``ridge_factor``)."""
        img0, img1 = self._kept(k - 1), self._kept(k)
        if img0 is None or img1 is None:
            return None
        T_wc0, T_wc1 = T_world_base0 @ self.T_base_cam, T_world_base1 @ self.T_base_cam
        n_cam, h = floor_in_camera(self.T_base_cam, n_base, floor_offset)
        pool = n_cam if pool_normal is None else floor_in_camera(self.T_base_cam, pool_normal, 0.0)[0]
        fit = self._fit(img0[1], img1[1], T_wc0, T_wc1, n_cam, h, (img0[2], img1[2]), pool, search, ridge)
        if fit is None:
            return None
        return RoadStep(k, fit.camera_m, base_distance(self.T_base_cam, T_wc0, T_wc1, fit.camera_m),
                        float(np.linalg.norm(T_wc1[:3, 3] - T_wc0[:3, 3])), fit.correlation, fit.n_pixels, fit.pitch_deg,
                        self.step_sigma_fraction(n_cam, h), fit.tilt_slope,
                        (np.linalg.inv(T_wc0) @ T_wc1)[:3, :3] if fit.tilt_slope != 0.0 else None)

    def _fit(self, img0: np.ndarray, img1: np.ndarray, T_wc0: np.ndarray, T_wc1: np.ndarray, n_cam: np.ndarray,
             h: float, masks: tuple[np.ndarray | None, np.ndarray | None], pool: np.ndarray,
             search: bool = True, ridge: bool = False) -> StepFit | None:
        """The step's fit: its own (``pitch_window`` 1, or the pitch not searched), or its length searched again on
        the pitch pooled over the last ``pitch_window`` searches (their median; searched at every step until the pool
        is full, then at every ``pitch_every``-th: one more search then moves the median little, and the search is
        four fifths of a step's cost; a change of the normal the pitches are pooled against, ``pool`` in the camera
        frame, the floor's attitude learnt, starts the pool over). ``search`` false: no search, the pool as it is."""
        c = self.cfg
        if c.pitch_search_deg <= 0:
            return measure_step(self.camera, img0, img1, T_wc0, T_wc1, n_cam, h, c if ridge else self._plain,
                                self.grid, masks, self._rays)
        if c.pitch_window <= 1:
            return measure_step(self.camera, img0, img1, T_wc0, T_wc1, n_cam, h, self._pitch_search, self.grid, masks, self._rays)
        if self._pitch_from is None or float(pool @ self._pitch_from) < math.cos(1e-3):
            self.pitches.clear()
            self._pitch_from = pool
        if search and (len(self.pitches) < max(1, c.pitch_window) or self._steps_since_search >= c.pitch_every - 1):
            self._steps_since_search = 0
            self.n_searches += 1
            fit = measure_step(self.camera, img0, img1, T_wc0, T_wc1, n_cam, h, self._pitch_search, self.grid, masks, self._rays)
            if fit is not None:
                self.pitches.append(fit.pitch_deg)
        elif search:  # a step measured again is no step of the search's count
            self._steps_since_search += 1
        if not self.pitches:
            return None
        pooled = pooled_pitch(list(self.pitches), c.pitch_sigmas, c.pitch_systematic_deg)
        on = measure_step(self.camera, img0, img1, T_wc0, T_wc1, rot_x(np.radians(pooled)) @ n_cam, h,
                          self._on_pitch_ridge if ridge else self._on_pitch, self.grid, masks, self._rays)
        return None if on is None else replace(on, pitch_deg=pooled)

    def pitch_tested(self) -> bool:
        """The floor's pitch a step is measured on has been tested: the pool holds MIN_PITCH_SEARCHES searches (or
        each step searches its own, or none is searched, or the pool is too small ever to be tested,
        ``pitch_window`` 2-4: the set-up's pitch is then the model)."""
        c = self.cfg
        return (c.pitch_search_deg <= 0 or c.pitch_window < MIN_PITCH_SEARCHES
                or len(self.pitches) >= MIN_PITCH_SEARCHES)

    def step_sigma_fraction(self, n_cam: np.ndarray, h: float) -> float:
        """A measured step's sigma as a share of its length: ``sigma_fraction``, widened while the floor's pitch is
        untested (``untested_pitch_deg``) by the length that pitch moves the step: a floor pitched by ``d`` about the
        camera's x axis moves each region point's depth by ``(x x n) . X / h`` times ``d`` (its depth in camera
        heights, for a camera looking along the floor), and the step with the region's depths (their median)."""
        c = self.cfg
        if c.untested_pitch_deg <= 0 or self.pitch_tested():
            return c.sigma_fraction
        _, X = region_rays(self.grid, n_cam, h, c)
        if len(X) == 0:
            return c.sigma_fraction
        per_rad = float(np.median(np.abs(X @ np.cross([1.0, 0.0, 0.0], n_cam)))) / h
        return math.hypot(c.sigma_fraction, per_rad * math.radians(c.untested_pitch_deg))


class RoadRegion:
    """``ground.road_region`` in the back end (``SlidingWindowBackend``): after each update, the new step measured at
    the estimate (``after_update``; not while the window ties ``max_floor_landmarks`` floor landmarks: the corners tell
    the floor then); before the next, its range factor (``add_factor``), while both poses are in the window and the
    floor may be tied (``FloorModel.ties_allowed``: with wheels, floor and wheels tested and agreeing,
    as for the floor's corners). Off (``ground.road_region.enabled`` false, or no ground cue): every call does
    nothing."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig, floor, kf_pose: dict[int, np.ndarray],
                 with_wheels: bool = False):
        self.cfg = cfg
        # With wheels, a step on an untested pitch waits until it is tested (the wheels carry the scale meanwhile);
        # without, it is tied as measured: the only metric cue of the run's first steps (``after_update``)
        self.with_wheels = with_wheels
        self.floor = floor  # the window's FloorModel: whether the floor is metric and may be tied, its normal
        self.kf_pose = kf_pose  # the window's keyframe poses (the smoother's; read here)
        on = cfg.ground.road_region.enabled and floor.use_ground
        rcfg = cfg.ground.road_region
        if with_wheels:  # the calibrated wheels bound the estimate's step: the coarse search is not moved out
            rcfg = rcfg.model_copy(update={"monocular_search_shifts": 0})
        self.cue = RoadRegionCue(camera, rcfg, camera.T_base_cam) if on else None
        self.ratio = float("nan")  # the last keyframe's measured step over the estimate's (nan: none)
        self.pitch_deg = float("nan")  # the floor's pitch against the assumed one it was measured on (nan: none)
        self.n_factors = 0  # range factors added to the smoother
        self.pending: list[RoadStep] = []  # measured, their factors not yet in the smoother
        self.untested: list[int] = []  # keyframes whose steps were measured on an untested pitch: measured again
        self.revised: dict[int, float] = {}  # those steps' base lengths (m) once measured again (for the cue check)

    def after_update(self, k: int, image: np.ndarray | None, mask: np.ndarray | None = None,
                     n_floor_tied: int = 0, w0: int | None = None) -> float | None:
        """Keyframe k's step measured at the new estimate (its factor goes into the next update). Returns the camera
        height the measurement implies in the estimate's scale (the known height times the estimate's step over the
        measured one; None: not measured), the floor's measurement for the cue check. ``n_floor_tied``: the floor
        landmarks the window ties to the floor (``road_region.max_floor_landmarks``); ``w0``: the window's first
        keyframe (the keyframes a rocking base's level floor is taken over; default: keyframe k-1 alone).

        With wheels, a step measured on a floor pitch not yet tested (``RoadRegionCue.pitch_tested``: the pool holds
        fewer than MIN_PITCH_SEARCHES searches) is recorded (``ratio``) but neither tied nor tested against the
        wheels: a pitch error moves its length 4-9% a degree (KITTI's set-up pitch, 1 deg off its road: 12-20%),
        more than the wheels' scale prior allows them (3%), so until its pitch is tested it could only pull the scale
        off. It is kept in ``untested`` and measured again, on the pooled pitch, at the keyframe whose search
        completes the pool; its factor then joins that keyframe's (``pending``) and its length goes to the cue check
        (``revised``, ``CueCheck.revise``). Without wheels it is tied as measured: nothing else tells the first steps' scale."""
        self.ratio = self.pitch_deg = float("nan")
        self.revised = {}
        self.pending = []
        if self.cue is None:
            return None
        self.cue.keep_image(k, image, mask)
        if not self.untested:
            self.cue.forget_before(k - 1)  # only the step to k needs an older image
        most = self.cfg.ground.road_region.max_floor_landmarks
        if (k == 0 or not self.floor.ground_active() or (k - 1) not in self.kf_pose
                or (most is not None and n_floor_tied >= most)):
            return None
        step = self._measure(k, w0, search=True)
        if step is None or step.camera_m <= 0:
            return None
        self.ratio = step.camera_m / step.estimate_camera_m
        self.pitch_deg = step.pitch_deg
        if not self.with_wheels:
            self.pending = [step]
            return self.floor.camera_height_m / self.ratio
        if not self.cue.pitch_tested():
            self.untested = [*self.untested[2 - KEPT_IMAGES:], k]  # older ones' images are gone
            return None
        again = [self._measure(j, w0, search=False) for j in self.untested if (j - 1) in self.kf_pose]
        self.untested = []
        self.pending = [s for s in again if s is not None and s.camera_m > 0] + [step]
        self.revised = {s.keyframe: s.base_m for s in self.pending[:-1]}
        if self.floor.cues is not None:  # the cue check's entries for those keyframes (before this one's test)
            self.floor.cues.revise(self.revised)
        return self.floor.camera_height_m / self.ratio

    def first_baseline(self, image: np.ndarray | None, mask: np.ndarray | None, T_base0_cam1: np.ndarray
                       ) -> float | None:
        """A monocular run's first baseline (the camera's step from keyframe 0 to 1, metres) measured by the floor's
        region, with keyframe 0's base as the world and ``T_base0_cam1`` keyframe 1's camera at the two views' rotation
        and direction (any baseline); None: off (``road_region.metric_start``) or not measured."""
        if self.cue is None or not self.cfg.ground.road_region.metric_start:
            return None
        n = self.floor.floor_normal_base()
        n_base = np.array([0.0, 0.0, 1.0]) if n is None else n
        fit = self.cue.first_step(image, mask, self.cue.T_base_cam, T_base0_cam1, n_base, self.floor.floor_offset(n))
        return None if fit is None or fit.camera_m <= 0 else fit.camera_m

    def _measure(self, k: int, w0: int | None, search: bool) -> RoadStep | None:
        """The step k-1 -> k on the floor as the window sees it from keyframe k-1 (``after_update``)."""
        assert self.cue is not None
        n = self.floor.floor_normal_base()  # the set-up's base z, or the floor's learnt normal when the floor uses it
        n_mount = np.array([0.0, 0.0, 1.0]) if n is None else n
        level = self.level_floor(k, k - 1 if w0 is None else w0, n_mount)
        if level is not None:
            n = level
        return self.cue.measure(k, self.kf_pose[k - 1], self.kf_pose[k], n_mount if n is None else n,
                                self.floor.floor_offset(n), n_mount, search=search, ridge=self.base_rocks())

    def base_rocks(self) -> bool:
        """The base rocks on its suspension (the floor model's test at its last plane fit: the window's keyframes
        tilting by more than ``ground.rocking_jitter_deg`` between keyframes): the tilt between two keyframes is
        then the suspension's, a degree and more, and vision's estimate of it when a step is measured is off by a
        tenth of a degree (the rendered rocking rooms), which the region's length takes up at 2-6% (``ridge_factor``)."""
        jitter = self.cfg.ground.rocking_jitter_deg
        return jitter is not None and bool(self.floor.base_rocking_deg > jitter)

    def level_floor(self, k: int, w0: int, n_mount: np.ndarray) -> np.ndarray | None:
        """The floor's normal in keyframe k-1's base frame when the base rocks on its suspension, else None (the
        floor's normal is ``n_mount`` in every keyframe's base frame).

        The base rocks when the window's keyframes' floor normals (``n_mount`` turned into the world by each
        keyframe's attitude) change by more than ``ground.rocking_jitter_deg`` between keyframes (their median: the
        floor model's test, ``attitude_jitter_deg``). The floor then lies along their mean (``level_up``: rocking
        is zero mean, and vision's keyframe rotations are good to a few hundredths of a degree while the tilt it
        rocks by is a degree and more), seen from keyframe k-1's attitude: its rocking is applied. With the
        set-up's normal instead, each degree of rocking is about 9% of a car's step measured by the region. Off by
        default (``road_region.level_when_rocking``): on the scale suite the fused runs came out 1.002x
        (docs/scale_suite.md)."""
        g = self.cfg.ground
        if not g.road_region.level_when_rocking or g.rocking_jitter_deg is None:
            return None
        Rs = [self.kf_pose[kk][:3, :3] for kk in range(w0, k + 1) if kk in self.kf_pose]
        if len(Rs) < MIN_ROCKING_KEYFRAMES:
            return None
        normals = np.array([R @ n_mount for R in Rs])
        if not attitude_jitter_deg(normals) > g.rocking_jitter_deg:
            return None
        mean = normals.mean(axis=0)
        up = level_up(normals, mean / np.linalg.norm(mean), g.level_select_deg)
        return self.kf_pose[k - 1][:3, :3].T @ up

    def add_factor(self, graph, w0: int) -> None:
        """The steps measured after the last update (the newest, and those measured again once their pitch was
        tested), each as a range factor between its two poses ``X(k-1)``, ``X(k)``, if both stay in the window
        through this update (``w0``: its start) and the floor may be tied."""
        from .factors import X, threshold

        steps, self.pending = self.pending, []
        if not self.floor.ties_allowed():
            return
        r = self.cfg.ground.road_region
        for step in steps:
            if step.keyframe - 1 <= w0:
                continue
            if np.isfinite(step.tilt_slope) and step.tilt_slope != 0.0 and self.cue is not None:
                graph.add(ridge_factor(X(step.keyframe - 1), X(step.keyframe), step, self.cue.T_base_cam,
                                       self.cfg.ground.robust, threshold(r.robust_k, 1, self.cfg)))
            else:
                graph.add(range_factor(X(step.keyframe - 1), X(step.keyframe), step.base_m,
                                       step.sigma_fraction * step.base_m, self.cfg.ground.robust,
                                       threshold(r.robust_k, 1, self.cfg)))
            self.n_factors += 1

    def forget(self) -> None:
        """The window was reset: no step is measured across it, none is pending."""
        self.ratio = self.pitch_deg = float("nan")
        self.pending, self.untested, self.revised = [], [], {}
        if self.cue is not None:
            self.cue.keep_image(-1, None)
