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
it: the correlation drops, the robust loss and the correlation threshold take it out), and the floor's attitude
against the camera is known. The last one is its bias: the region's rays meet the floor at grazing angles, so a
tilt error ``da`` moves ``s`` by about ``da / tan(depression)`` (9% a degree with a car's camera looking 6-10 m ahead).
The normal is the floor's learnt one (``FloorAttitude``: a mount pitched against ``T_base_cam``) when known, else the
set-up's (the base's z axis: a rocking base's tilt between keyframes is not applied; the estimate's attitude
against the world, measured as the alternative, drifts by tenths of a degree on a long street and biased the steps
by 2.6%). A step's sigma is ``sigma_fraction`` of its length. Masked pixels (``frontend`` masks: a bonnet, the
robot's own body) are left out of the region in both images.

The measurement (``measure_step``, ``RoadRegionCue``: which images, which step) is numpy and OpenCV, tested on its own
(``tests/test_road_region.py``); ``RoadRegion`` is the smoother's side (when to measure, when its range factor may go
in), and ``range_factor`` the one GTSAM factor.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import BackendConfig, RoadRegionConfig
from ..geometry import rot_y

# The search (``_search``): a coarse grid of COARSE_STEPS lengths over +-COARSE_SPAN (log) around the estimate's step,
# a parabola through the best one and its neighbours, then REFINE_ROUNDS rounds of the direction's sideways angle
# and the length on grids of FINE_STEPS (the length over 3 FINE_SPAN, the angle over search_direction_deg), each
# round on a third of the last span.
COARSE_STEPS = 29
COARSE_SPAN = 0.35
FINE_STEPS = 9
FINE_SPAN = 0.03
REFINE_ROUNDS = 3  # rounds of the alternating search (direction, length), each on a third of the span
REMAP_COLS = 16384  # cv2.remap's map is folded into rows of this many points (it takes fewer than SHRT_MAX columns)
BLUR_SIGMA_PX = 1.0  # the images are smoothed before sampling (the warp's linear interpolation then behaves)


@dataclass(frozen=True)
class RoadStep:
    """One keyframe step measured by the floor's region: its length between the cameras and between the bases."""

    keyframe: int  # the step k-1 -> k
    camera_m: float  # the cameras' distance, s h
    base_m: float  # the base origins' distance (what the range factor ties)
    estimate_camera_m: float  # the estimate's camera distance when measured
    correlation: float  # at the best scale
    n_pixels: int


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


def region_rays(grid: tuple[np.ndarray, np.ndarray], n_cam: np.ndarray, h: float, cfg: RoadRegionConfig
                ) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of ``grid`` (``pixel_grid``) whose rays meet the floor within the region ahead (``near_heights``
    to ``far_heights`` camera heights along the optical axis, ``half_width_heights`` beside it), and those rays
    scaled to meet the floor: ``(uv (N, 2) int, X (N, 3))``, X on the plane ``n . X = h``."""
    uv, rays = grid
    ny = rays @ n_cam
    ok = ny > 1e-6
    lam = np.where(ok, h / np.where(ok, ny, 1.0), 0.0)
    X = rays * lam[:, None]
    ok &= (X[:, 2] >= cfg.near_heights * h) & (X[:, 2] <= cfg.far_heights * h)
    ok &= np.abs(X[:, 0]) <= cfg.half_width_heights * h
    uv, X = uv[ok], X[ok]
    if len(uv) > cfg.max_pixels:  # an even subsample
        keep = np.linspace(0, len(uv) - 1, cfg.max_pixels).round().astype(int)
        uv, X = uv[keep], X[keep]
    return uv, X


def smoothed(image: np.ndarray) -> np.ndarray:
    """The float image the measurement samples."""
    return cv2.GaussianBlur(image.astype(np.float32), (0, 0), BLUR_SIGMA_PX)


def _zncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum()) / den if den > 1e-9 else -1.0


class _Warp:
    """The correlation of the floor region of image k-1 with image k warped by the floor's homography, per s."""

    def __init__(self, camera: CameraModel, img0: np.ndarray, img1: np.ndarray, uv0: np.ndarray, X0: np.ndarray,
                 R: np.ndarray, t_dir: np.ndarray, n_cam: np.ndarray, h: float, min_pixels: int,
                 mask1: np.ndarray | None = None):
        self.camera, self.img1, self.mask1 = camera, img1, mask1
        self.pinhole = not camera.has_distortion
        self.a = img0[uv0[:, 1], uv0[:, 0]].astype(np.float32)
        self.RX = (X0 @ R.T).astype(np.float32)  # (R X) for each floor point, camera k
        self.nX = (X0 @ n_cam).astype(np.float32)  # n . X for each point (h on the floor)
        self.set_direction(t_dir)
        self.n_last = 0
        self.min_pixels = min_pixels
        self.bounds = (1.0, camera.width - 2.0, 1.0, camera.height - 2.0)

    def set_direction(self, t_dir: np.ndarray) -> None:
        self.tn = np.outer(self.nX, t_dir).astype(np.float32)  # t_dir (n . X) per point: s times it is the translation

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

    def correlation(self, s: float) -> tuple[float, int]:
        return self.correlations(np.array([s]), self.tn[None])[0], self.n_last

    def correlations(self, ss: np.ndarray, tns: np.ndarray) -> list[float]:
        """``correlation`` of the lengths ``ss`` (S,), each with its direction's ``t_dir (n . X)`` (``tns``: (S, N, 3)
        or (1, N, 3) for one direction), in one pass: the same numbers as one call per length, with the numpy and
        OpenCV work done once for all S (``n_last``: the last one's pixels)."""
        uv, front = self._project(self.RX[None] + ss.astype(np.float32)[:, None, None] * tns)  # (S, N, ...)
        u0, u1, v0, v1 = self.bounds
        inside = front & (uv[..., 0] >= u0) & (uv[..., 0] <= u1) & (uv[..., 1] >= v0) & (uv[..., 1] <= v1)
        if self.mask1 is not None:  # samples landing on masked pixels of image k are no floor
            idx = np.nonzero(inside)
            p = uv[idx] + 0.5
            off = self.mask1[p[:, 1].astype(int), p[:, 0].astype(int)] == 0
            inside[idx[0][off], idx[1][off]] = False
        counts = inside.sum(axis=1)
        self.n_last = int(counts[-1])
        b_all = _remap(self.img1, uv[inside])
        out, at = [], 0
        for i, n in enumerate(counts):
            b, at = b_all[at:at + n], at + n
            out.append(_zncc(self.a[inside[i]], b) if n >= self.min_pixels else -1.0)
        return out

    def flow_px(self, s: float) -> float:
        """Median displacement of the region's pixels between s = 0 (rotation only) and s."""
        uv0, f0 = self.pixels(0.0)
        uv1, f1 = self.pixels(s)
        ok = f0 & f1
        return float(np.median(np.linalg.norm(uv1[ok] - uv0[ok], axis=1))) if ok.any() else 0.0


def _remap(img: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``img`` sampled (bilinear) at the points ``m`` (M, 2): one ``cv2.remap``, its map folded into rows (remap takes
    at most SHRT_MAX columns); each point's value is its own, however the map is folded."""
    n = len(m)
    if n == 0:
        return np.zeros(0, np.float32)
    cols = min(n, REMAP_COLS)
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = m[:, 0], m[:, 1]
    return cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR).ravel()[:n]


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


def measure_step(camera: CameraModel, img0: np.ndarray, img1: np.ndarray, T_world_cam0: np.ndarray,
                 T_world_cam1: np.ndarray, n_cam: np.ndarray, h: float, cfg: RoadRegionConfig,
                 grid: tuple[np.ndarray, np.ndarray] | None = None,
                 masks: tuple[np.ndarray | None, np.ndarray | None] = (None, None)) -> tuple[float, float, int] | None:
    """The camera step's metric length from the floor region (``img0``/``img1``: ``smoothed`` images of the two
    keyframes; the poses give the rotation and the direction).

    The estimate's direction is not exact, and a sideways error of it shifts the floor's pixels sideways by an
    amount that grows with the length: a road's lane lines make that costly, so a shorter step would win (10% on a
    curve for a direction 0.6 deg off). The direction's sideways angle is searched too (``search_direction_deg``),
    alternately with the length: it moves the pixels across the image, the length along their rays, so the two
    separate. Returns ``(length m, correlation, pixels)``, or None when the floor region does not measure it: too
    few pixels, too little motion of the floor in the image, the correlation below ``min_correlation``, or the
    length's peak at the edge of its search."""
    T_c1_c0 = np.linalg.inv(T_world_cam1) @ T_world_cam0
    R, t = T_c1_c0[:3, :3], T_c1_c0[:3, 3]
    d_est = float(np.linalg.norm(t))
    if d_est < 1e-6 or h <= 0:
        return None
    uv0, X0 = region_rays(grid if grid is not None else pixel_grid(camera, cfg.step_px), n_cam, h, cfg)
    if masks[0] is not None:  # the pixels masked in image k-1 are no floor
        usable = masks[0][uv0[:, 1], uv0[:, 0]] > 0
        uv0, X0 = uv0[usable], X0[usable]
    if len(uv0) < cfg.min_pixels:
        return None
    t_dir = t / d_est
    warp = _Warp(camera, img0, img1, uv0, X0, R, t_dir, n_cam, h, cfg.min_pixels, masks[1])
    s_est = d_est / h
    if warp.flow_px(s_est) < cfg.min_flow_px:
        return None
    return _search(warp, t_dir, s_est, h, cfg)


def _search(warp: _Warp, t_dir: np.ndarray, s_est: float, h: float, cfg: RoadRegionConfig
            ) -> tuple[float, float, int] | None:
    """``measure_step``'s search: a coarse grid of the length around the estimate's, then rounds of the direction's
    sideways angle and the length, each on a third of the last span."""
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

    c, inside = line(0, COARSE_SPAN, COARSE_STEPS)
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
    return float(np.exp(p[0])) * h, c_best, warp.n_last


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


def range_factor(key0: int, key1: int, base_m: float, sigma_m: float, robust_kind, robust_k: float):
    """The step's length as a range factor between the two base poses (GTSAM's native ``RangeFactorPose3``)."""
    import gtsam

    from .factors import robust

    noise = robust(gtsam.noiseModel.Isotropic.Sigma(1, sigma_m), robust_kind, robust_k)
    return gtsam.RangeFactorPose3(key0, key1, float(base_m), noise)


class RoadRegionCue:
    """The back end's side: keeps the last keyframe's image, measures each step once the window has estimated it,
    and hands its range factor to the next update (both poses are still in the window then)."""

    def __init__(self, camera: CameraModel, cfg: RoadRegionConfig, T_base_cam: np.ndarray):
        self.camera, self.cfg, self.T_base_cam = camera, cfg, T_base_cam
        self.grid = pixel_grid(camera, cfg.step_px)
        # (keyframe, smoothed image, mask) of the newest keyframe, and of the one before it
        self._image: tuple[int, np.ndarray, np.ndarray | None] | None = None
        self._previous: tuple[int, np.ndarray, np.ndarray | None] | None = None
        self.pending: RoadStep | None = None  # measured, its factor not yet in the smoother

    def keep_image(self, k: int, image: np.ndarray | None, mask: np.ndarray | None = None) -> None:
        """Keyframe k's image (grey, as measured) and its usable pixels (0: masked; None: all); no image: the step
        to it is not measured."""
        self._previous = self._image
        self._image = None if image is None else (k, smoothed(image), mask)

    def measure(self, k: int, T_world_base0: np.ndarray, T_world_base1: np.ndarray, n_base: np.ndarray,
                floor_offset: float) -> RoadStep | None:
        """The step k-1 -> k from the floor region, at the estimate's poses (after keyframe k's update); kept as
        ``pending`` for the next update. ``n_base``, ``floor_offset``: the floor in keyframe k-1's base frame."""
        self.pending = None
        if self._image is None or self._previous is None or self._image[0] != k or self._previous[0] != k - 1:
            return None
        T_wc0, T_wc1 = T_world_base0 @ self.T_base_cam, T_world_base1 @ self.T_base_cam
        n_cam, h = floor_in_camera(self.T_base_cam, n_base, floor_offset)
        got = measure_step(self.camera, self._previous[1], self._image[1], T_wc0, T_wc1, n_cam, h, self.cfg, self.grid,
                           (self._previous[2], self._image[2]))
        if got is None:
            return None
        camera_m, corr, n = got
        step = RoadStep(k, camera_m, base_distance(self.T_base_cam, T_wc0, T_wc1, camera_m),
                        float(np.linalg.norm(T_wc1[:3, 3] - T_wc0[:3, 3])), corr, n)
        self.pending = step
        return step

    def take_pending(self) -> RoadStep | None:
        step, self.pending = self.pending, None
        return step


class RoadRegion:
    """``ground.road_region`` in the back end (``SlidingWindowBackend``): after each update, the new step measured at
    the estimate (``after_update``; not while the window ties ``max_floor_landmarks`` floor landmarks: the corners tell
    the floor then); before the next, its range factor (``add_factor``), while both poses are in the window and the
    floor may be tied (``FloorModel.ties_allowed``: with wheels, floor and wheels tested and agreeing,
    as for the floor's corners). Off (``ground.road_region.enabled`` false, or no ground cue): every call does
    nothing."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig, floor, kf_pose: dict[int, np.ndarray]):
        self.cfg = cfg
        self.floor = floor  # the window's FloorModel: whether the floor is metric and may be tied, its normal
        self.kf_pose = kf_pose  # the window's keyframe poses (the smoother's; read here)
        on = cfg.ground.road_region.enabled and floor.use_ground
        self.cue = RoadRegionCue(camera, cfg.ground.road_region, camera.T_base_cam) if on else None
        self.ratio = float("nan")  # the last keyframe's measured step over the estimate's (nan: none)
        self.n_factors = 0  # range factors added to the smoother

    def after_update(self, k: int, image: np.ndarray | None, mask: np.ndarray | None = None,
                     n_floor_tied: int = 0) -> float | None:
        """Keyframe k's step measured at the new estimate (its factor goes into the next update). Returns the camera
        height the measurement implies in the estimate's scale (the known height times the estimate's step over the
        measured one; None: not measured), the floor's measurement for the cue check. ``n_floor_tied``: the floor
        landmarks the window ties to the floor (``road_region.max_floor_landmarks``)."""
        self.ratio = float("nan")
        if self.cue is None:
            return None
        self.cue.keep_image(k, image, mask)
        most = self.cfg.ground.road_region.max_floor_landmarks
        if (k == 0 or not self.floor.ground_active() or (k - 1) not in self.kf_pose
                or (most is not None and n_floor_tied >= most)):
            self.cue.pending = None
            return None
        n = self.floor.floor_normal_base()  # the set-up's base z, or the floor's learnt normal when the floor uses it
        step = self.cue.measure(k, self.kf_pose[k - 1], self.kf_pose[k], np.array([0.0, 0.0, 1.0]) if n is None else n,
                                self.floor.floor_offset(n))
        if step is None or step.camera_m <= 0:
            return None
        self.ratio = step.camera_m / step.estimate_camera_m
        return self.floor.camera_height_m / self.ratio

    def add_factor(self, graph, w0: int) -> None:
        """The last measured step as a range factor between its two poses ``X(k-1)``, ``X(k)``, if both stay in the
        window through this update (``w0``: its start) and the floor may be tied."""
        from .factors import X, threshold

        step = None if self.cue is None else self.cue.take_pending()
        if step is None or step.keyframe - 1 <= w0 or not self.floor.ties_allowed():
            return
        r = self.cfg.ground.road_region
        graph.add(range_factor(X(step.keyframe - 1), X(step.keyframe), step.base_m, r.sigma_fraction * step.base_m,
                               self.cfg.ground.robust, threshold(r.robust_k, 1, self.cfg)))
        self.n_factors += 1

    def forget(self) -> None:
        """The window was reset: no step is measured across it, none is pending."""
        self.ratio = float("nan")
        if self.cue is not None:
            self.cue.keep_image(-1, None)
            self.cue.pending = None
