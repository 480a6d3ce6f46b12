"""The ground-plane cue: which landmarks lie on the floor, and the metric scale it implies.

A ground robot's camera sits at a known height above the floor (``T_base_cam``, base origin on
the floor), and the floor is in view. Landmarks below the horizon of the base frame, close
enough, are candidates; a plane fitted to them with RANSAC in the base frame of the newest
keyframe is accepted only when it is nearly level and lies near the expected height
(within ``ground.height_tolerance``). Its inliers are floor landmarks: the window ties them to
the ground plane with a factor (``factors.ground_factor``). Where the assumption breaks (a
ramp ahead, boxes, a floor without texture, a camera that does not see the floor) no plane
passes these checks, and the cue switches itself off for that keyframe.

A base that rocks on its suspension (bumps, vibration) breaks one more assumption: the floor is
then not the xy plane of each keyframe's base frame, and tying a floor point to its birth
keyframe's tilted plane turns the rocking into a height error, which the smoother partly pays
with scale. ``attitude_jitter_deg`` tells a rocking base from a level one (the median change of
the base's tilt between consecutive keyframes), and ``level_up`` gives the floor's normal that
the floor points are then measured along instead (``factors.level_ground_factor``). And a camera
mount is seldom calibrated to better than a degree: ``FloorAttitude`` learns the floor's normal in
the base frame from the planes fitted so far, so that a mount's pitch or roll error does not turn
into a scale error (1 deg of pitch made 5.5% of scale error on the rendered loop);
``tilt_significant`` says when that tilt is the mount's, and ``levelled_mount`` corrects
``T_base_cam`` by it. ``off_floor`` tells which tied floor landmarks, seen again from later
keyframes, turn out to lie off the floor (a kerb beside it), so that they lose their ground factor;
``beside_track`` tells which the base has driven past beside its track (``ground.corridor_heights``: the ground the
wheels roll on is the floor at the camera's height, the ground beside it only by assumption).

Pure numpy: no GTSAM here, so the detector is tested on its own.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..config import GroundConfig
from ..geometry import so3_exp

RANSAC_ITERATIONS = 60
# The ground factor measures a floor point's elevation seen from the base origin, which is undefined
# for a point right at the origin: floor candidates keep this many camera heights away from it (only a
# camera mounted behind the base origin can see such a point at all).
MIN_BASE_RANGE_HEIGHTS = 0.2


@dataclass
class PlaneFit:
    """Plane ``n . p = -d`` in the base frame (n unit, pointing up), with its inliers."""

    normal: np.ndarray  # (3,)
    offset: float  # d: the plane is n.p + d = 0
    inliers: np.ndarray  # bool mask over the points it was fitted to
    tilt_deg: float  # angle between n and the base z axis
    camera_height_m: float  # distance of the camera above the plane (in the estimate's scale)


def floor_candidates(p_base: np.ndarray, cam_in_base: np.ndarray, camera_height_m: float,
                     cfg: GroundConfig) -> np.ndarray:
    """Mask of points below the horizon by at least ``min_depression_deg``, within range, and not at
    the base origin."""
    if len(p_base) == 0:
        return np.zeros(0, bool)
    rel = p_base - cam_in_base
    horiz = np.hypot(rel[:, 0], rel[:, 1])
    depression = np.degrees(np.arctan2(-rel[:, 2], np.maximum(horiz, 1e-9)))
    off_origin = np.hypot(p_base[:, 0], p_base[:, 1]) >= MIN_BASE_RANGE_HEIGHTS * camera_height_m
    return ((depression >= cfg.min_depression_deg) & (horiz <= cfg.max_range_heights * camera_height_m)
            & (rel[:, 0] > 0.0) & off_origin)


def _inlier_threshold(p_base: np.ndarray, cam_in_base: np.ndarray, camera_height_m: float,
                      cfg: GroundConfig) -> np.ndarray:
    """Per point: a share of the camera height plus a share of the range (depth noise grows with it)."""
    horiz = np.hypot(p_base[:, 0] - cam_in_base[0], p_base[:, 1] - cam_in_base[1])
    return cfg.inlier_height_fraction * camera_height_m + cfg.inlier_range_fraction * horiz


def fit_floor_plane(p_base: np.ndarray, cam_in_base: np.ndarray, camera_height_m: float, cfg: GroundConfig,
                    rng: np.random.Generator, metric_scale_known: bool = True) -> PlaneFit | None:
    """RANSAC plane through floor candidates (base frame), or None if no plane passes the checks.

    With ``metric_scale_known`` the plane must also lie within ``height_tolerance`` of the known
    camera height; without (monocular start) any height is accepted: it then fixes the scale.
    """
    n_pts = len(p_base)
    if n_pts < cfg.min_points:
        return None
    thr = _inlier_threshold(p_base, cam_in_base, camera_height_m if metric_scale_known else 1.0, cfg)
    # All hypotheses at once: planes through random triples of points, kept if nearly level.
    tri = rng.integers(0, n_pts, (RANSAC_ITERATIONS, 3))  # a repeated index gives no normal: dropped below
    a, b, c = p_base[tri[:, 0]], p_base[tri[:, 1]], p_base[tri[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n = n[ok] / norm[ok, None]
    a = a[ok]
    n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
    level = np.degrees(np.arccos(np.clip(n[:, 2], -1.0, 1.0))) <= cfg.max_tilt_deg
    n, a = n[level], a[level]
    if len(n) == 0:
        return None
    dist = np.abs(np.einsum("hj,nj->hn", n, p_base) - np.einsum("hj,hj->h", n, a)[:, None])  # (H, N)
    if metric_scale_known:
        hyp_scale = np.ones(len(n))
    else:
        hyp_scale = np.maximum(np.einsum("hj,hj->h", n, cam_in_base[None, :] - a), 1e-6)
    inl_all = dist <= thr[None, :] * hyp_scale[:, None]
    counts = inl_all.sum(axis=1)
    best = int(np.argmax(counts))
    best_inl, best_count = inl_all[best], int(counts[best])
    if best_count < cfg.min_points:
        return None
    # Least-squares refit on the inliers (smallest singular vector of the centred points).
    P = p_base[best_inl]
    centre = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - centre)
    n = vt[2] if vt[2, 2] >= 0 else -vt[2]
    d = -float(n @ centre)
    tilt = float(np.degrees(np.arccos(np.clip(n[2], -1.0, 1.0))))
    height = float(n @ cam_in_base + d)
    if tilt > cfg.max_tilt_deg or height <= 0:
        return None
    if metric_scale_known and abs(height / camera_height_m - 1.0) > cfg.height_tolerance:
        return None
    inliers = np.abs(p_base @ n + d) <= thr * (1.0 if metric_scale_known else height)
    if int(inliers.sum()) < cfg.min_points:
        return None
    return PlaneFit(n, d, inliers, tilt, height)


def floor_mask(p_world: np.ndarray, T_world_base: np.ndarray, T_base_cam: np.ndarray, camera_height_m: float,
               cfg: GroundConfig, rng: np.random.Generator, metric_scale_known: bool = True
               ) -> tuple[np.ndarray, PlaneFit | None]:
    """Which world points lie on the floor seen from a keyframe; all False when no floor plane passes."""
    mask = np.zeros(len(p_world), bool)
    if len(p_world) == 0:
        return mask, None
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    p_base = (np.asarray(p_world) - t) @ R
    cam = T_base_cam[:3, 3]
    cand = floor_candidates(p_base, cam, camera_height_m, cfg)
    fit = fit_floor_plane(p_base[cand], cam, camera_height_m, cfg, rng, metric_scale_known)
    if fit is None:
        return mask, None
    idx = np.nonzero(cand)[0]
    mask[idx[fit.inliers]] = True
    return mask, fit


def camera_height_up_to_scale(p_cam: np.ndarray, cfg: GroundConfig, rng: np.random.Generator,
                              refine: bool = False) -> float | None:
    """The camera's height above the floor plane under points given around the camera centre (base
    orientation), in the points' own unit: a monocular run's scale is ``camera height / this``. None: no
    floor plane passes. The camera's offset inside the base is metric while such points are not, hence
    the camera-centred frame. ``refine``: a second fit measures ranges in camera heights of the first."""
    height = 1.0
    origin = np.zeros(3)
    for _ in range(2 if refine else 1):
        cand = floor_candidates(p_cam, origin, height, cfg)
        fit = fit_floor_plane(p_cam[cand], origin, height, cfg, rng, metric_scale_known=False)
        if fit is None or fit.camera_height_m <= 1e-6:
            return None
        height = fit.camera_height_m
    return height


# Untying floor landmarks off the floor (``off_floor``): fewer tied landmarks than this and nothing is judged;
# the robust sigma is at least this share of the camera height (a window of near-perfect heights must not
# untie the points a millimetre off).
UNTIE_MIN_POINTS = 10
UNTIE_MIN_SIGMA_HEIGHTS = 0.01
# A raised surface shows as a lopsided spread: at least this many times as many heights beyond the threshold
# above the median as below it, and UNTIE_MIN_EXCESS more. Otherwise the tails are the floor's own noise, and
# untying them only thins the scale's evidence (always untying: 19 plain runs 0.59x-1.64x, one test's loop
# 1.06 -> 1.30x its Sim(3) ATE).
UNTIE_LOPSIDED = 2.0
UNTIE_MIN_EXCESS = 5


def off_floor(heights_m: np.ndarray, k_sigma: float, min_sigma_m: float) -> np.ndarray:
    """Which tied floor landmarks stray from the floor: heights (above the floor of the keyframe that tied
    each) farther than ``k_sigma`` robust sigmas (1.4826 x MAD, at least ``min_sigma_m``) from their median.

    The plane fit at a landmark's birth judges it from two or three views; a raised surface beside the floor
    (a kerb, a pavement, a mat a few centimetres up) is then within its band, and tying it to the floor pulls
    the scale by its height over the camera height. Seen again from the window's later keyframes its height is
    known better, and it stands out of the heights of the floor's points, above them. Only when the spread is
    lopsided upwards (``UNTIE_LOPSIDED``, ``UNTIE_MIN_EXCESS``) is anything untied, and then on both sides, so
    that the floor's height is not biased by cutting one tail of its noise."""
    h = np.asarray(heights_m, float)
    none = np.zeros(len(h), bool)
    if len(h) < UNTIE_MIN_POINTS:
        return none
    med = float(np.median(h))
    sigma = max(1.4826 * float(np.median(np.abs(h - med))), min_sigma_m)
    above, below = h - med > k_sigma * sigma, h - med < -k_sigma * sigma
    if above.sum() < UNTIE_LOPSIDED * below.sum() + UNTIE_MIN_EXCESS:
        return none
    return above | below


# ``beside_track``: the track's positions are kept this share of the corridor's half width apart at least.
TRACK_MIN_STEP = 0.25


def _moved(track: np.ndarray, min_step_m: float) -> np.ndarray:
    """The track's positions without those less than ``min_step_m`` from the last one kept (a base standing still
    leaves no segment along which a point could have been passed)."""
    keep = [0] if len(track) else []
    for i in range(1, len(track)):
        if np.linalg.norm(track[i] - track[keep[-1]]) >= min_step_m:
            keep.append(i)
    out = track[keep]
    if len(keep) > 1 and keep[-1] != len(track) - 1:
        out[-1] = track[-1]  # the newest position ends the track
    return out


def beside_track(p_world: np.ndarray, track_world: np.ndarray, max_offset_m: float) -> np.ndarray:
    """Which points the base has driven past at more than ``max_offset_m`` from its track.

    ``track_world`` (M, 3): the base origins of the window's keyframes in order (on the floor: the base origin lies
    on it), thinned to steps of at least a quarter of ``max_offset_m``: a base standing still or turning in place,
    whose estimated position jitters by millimetres, adds no segment that could point anywhere. A point's offset is its
    distance to the nearest segment of that polyline; it counts as passed only when its nearest point on the track
    lies between the first and the last keyframe: a point still ahead of the newest keyframe (or behind the oldest)
    has no track beside it to be judged against yet."""
    p = np.asarray(p_world, float).reshape(-1, 3)
    out = np.zeros(len(p), bool)
    track = _moved(np.asarray(track_world, float).reshape(-1, 3), TRACK_MIN_STEP * max_offset_m)
    if len(p) == 0 or len(track) < 2:
        return out
    a, b = track[:-1], track[1:]  # segments (S, 3)
    ab = b - a
    length2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
    u = np.einsum("nsj,sj->ns", p[:, None, :] - a[None], ab) / length2  # (N, S) position along each segment
    uc = np.clip(u, 0.0, 1.0)
    nearest = a[None] + uc[..., None] * ab[None]
    dist = np.linalg.norm(p[:, None, :] - nearest, axis=2)
    s = np.argmin(dist, axis=1)
    rows = np.arange(len(p))
    ahead = (s == len(ab) - 1) & (u[rows, s] >= 1.0)
    behind = (s == 0) & (u[rows, s] <= 0.0)
    return (dist[rows, s] > max_offset_m) & ~ahead & ~behind


def floor_landmarks_to_untie(T_world_tying: np.ndarray, p_world: np.ndarray, n_base: np.ndarray | None, offset: float,
                             track_world: np.ndarray, cfg: GroundConfig, camera_height_m: float
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Which tied floor landmarks lose their ground factors after an update: those whose heights stray from the others'
    (``off_floor``, ``ground.untie_sigmas``) or that the base drove past beside its track (``beside_track``,
    ``ground.corridor_heights``), and of them, those untied for the track alone. ``T_world_tying`` (N, 4, 4): the base
    pose of the keyframe that tied each; ``n_base``/``offset``: the floor in those base frames (None: the base's z)."""
    off = np.zeros(len(p_world), bool)
    if cfg.untie_sigmas is not None:
        up = np.array([0.0, 0.0, 1.0]) if n_base is None else n_base
        # Height along ``up`` in the tying keyframe's base frame: up . R^T (p - t), for all points at once.
        heights = np.einsum("nij,ni,j->n", T_world_tying[:, :3, :3], p_world - T_world_tying[:, :3, 3], up) - offset
        off = off_floor(heights, cfg.untie_sigmas, UNTIE_MIN_SIGMA_HEIGHTS * camera_height_m)
    beside = np.zeros(len(p_world), bool)
    if cfg.corridor_heights is not None:
        beside = beside_track(p_world, track_world, cfg.corridor_heights * camera_height_m) & ~off
    return off | beside, beside


def attitude_jitter_deg(z_axes: np.ndarray) -> float:
    """Median angle (deg) between the z axes of consecutive keyframes' bases, (N, 3) in order.

    Turning, driving up a ramp or standing still leave it near zero (a ramp tilts the base over a
    few keyframes only, the median ignores them); a chassis rocking on its suspension moves it by
    about the rocking amplitude. 0 for fewer than two axes.
    """
    z = np.asarray(z_axes, float)
    if len(z) < 2:
        return 0.0
    cos = np.clip(np.einsum("ij,ij->i", z[1:], z[:-1]), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cos))))


def level_up(z_axes: np.ndarray, floor_normal: np.ndarray, select_deg: float) -> np.ndarray:
    """The floor's normal for a rocking base (world frame, unit).

    The mean z axis of the keyframes whose base lies within ``select_deg`` of the fitted floor
    plane's normal ``floor_normal`` (world frame): rocking is zero-mean, so the mean over the window
    removes it, and the selection keeps keyframes that stood on another plane (the other side of a
    ramp's edge) out. The fitted normal itself when no keyframe is that close.
    """
    n = np.asarray(floor_normal, float)
    n = n / np.linalg.norm(n)
    z = np.asarray(z_axes, float).reshape(-1, 3)
    near = z[np.einsum("ij,j->i", z, n) >= np.cos(np.radians(select_deg))]
    if len(near) == 0:
        return n
    up = near.mean(axis=0)
    return up / np.linalg.norm(up)


# Above this tilt of the floor in the base frame (deg), and three standard errors, the camera mount is
# suspected (and with ground.mount_calibration auto, corrected): level rendered runs learn 0.03-0.1 deg,
# rocking ones up to 0.36 (2.5 deg of rocking, few fits: standard error larger), a mount pitched by
# 0.5 / 1 deg 0.46 / 0.89.
MOUNT_TILT_MIN_DEG = 0.3
# ``FloorAttitude.add_motion``: steps further than this from the base's x axis (turns, sideways moves) are left out.
MOTION_MAX_AZIMUTH_DEG = 20.0
# ``FloorAttitude.normal`` with the motion's tilt: the median of this many latest steps (the floor under the camera
# now: the body pitches on its suspension with the road and the load, KITTI 01's camera by 0.7 deg in 3 s).
MOTION_WINDOW_STEPS = 10


def range_sigmas_m(sigma_m: float, own_sigma_m: float, p_base: np.ndarray, tilt_sigma_rad: float
                   ) -> tuple[float, float]:
    """A floor point's height sigma and the sigma its robust threshold is counted in, at its range from the base
    (``p_base``, base frame): ``sigma_m`` and the point's own sigma ``own_sigma_m``, each widened by the floor's
    attitude error against the base (``ground.sigma_tilt_deg``), which moves a point's height by its range times the
    angle. The floor's tilt under the camera is one error every point of a keyframe shares, and far points carry more
    of it: a camera pitched 1 deg on its mount puts a road point 10 m ahead 17 cm off a 1.65 m camera's floor (10%),
    while the factor without it would weigh that point as if its height were known to 3%. 0 rad: unchanged."""
    tilt = float(np.tan(tilt_sigma_rad))
    if tilt == 0.0:
        return sigma_m, own_sigma_m
    e2 = float(p_base[0] ** 2 + p_base[1] ** 2) * tilt * tilt
    return float(np.sqrt(sigma_m**2 + e2)), float(np.sqrt(own_sigma_m**2 + e2))


def tilt_significant(tilt_deg: float, standard_error_deg: float) -> bool:
    """Whether a learnt floor tilt says the camera mount is off its calibration."""
    return tilt_deg > max(MOUNT_TILT_MIN_DEG, 3.0 * standard_error_deg)


class FloorAttitude:
    """The floor's normal in the base frame, learnt from the floor planes fitted at the keyframes (its pitch, with
    ``from_motion``, from the direction of the base's steps: ``add_motion``).

    ``T_base_cam`` says where the camera sits on a base whose xy plane is the floor; a mount pitched or
    rolled by a degree against it tilts every floor point's height by its range times that angle, which
    the ground factor would pay with scale. The plane fitted at each keyframe (base frame) measures the
    floor's normal there, noisily (0.1-0.5 deg on the rendered sequences) and, on a rocking base or at a
    ramp's edge, off by the rocking or the ramp for a while; the median over the last ``max_fits`` fits
    is the mount's static error without them; it is ``ready`` from ``min_fits`` fits on.
    """

    def __init__(self, min_fits: int, max_fits: int, from_motion: bool = False):
        self.min_fits = min_fits
        self._xy: deque[tuple[float, float]] = deque(maxlen=max_fits)
        self._normal: np.ndarray | None = None  # the median, computed once per fit (read several times)
        # ``ground.mount_from_motion``: the tilt toward +x from the direction the base moves in (``add_motion``).
        self.from_motion = from_motion
        self._motion_x: deque[float] = deque(maxlen=max_fits)

    def add_motion(self, d_base: np.ndarray) -> bool:
        """One keyframe step's direction of motion, from vision alone (the front end's two-view direction), in the
        base frame ``T_base_cam`` defines at the step's first keyframe. Returns whether it was taken.

        A ground robot moves along its floor, so the floor's normal is perpendicular to every step: a step
        along the base's x axis that climbs by an angle e in the set-up's base frame says the floor is tilted
        by -e toward +x, i.e. the camera is pitched by e against its calibration (forward or reversing alike:
        the tilt is ``-d_z / d_x``). Only steps within ``MOTION_MAX_AZIMUTH_DEG`` of the x axis are taken: a
        sideways step's climb is the mount's roll, which the plane fits measure. Unlike a plane fit it needs
        no floor texture and no point on the floor, and a kerb or a raised pavement does not bias it."""
        d = np.asarray(d_base, float)
        horizontal = float(np.hypot(d[0], d[1]))
        if horizontal <= 0.0 or abs(d[0]) < horizontal * np.cos(np.radians(MOTION_MAX_AZIMUTH_DEG)):
            return False
        nx = -float(d[2]) / float(d[0])
        self._motion_x.append(nx / float(np.sqrt(1.0 + nx * nx)))
        self._normal = None
        return True

    def _motion_ready(self) -> bool:
        return self.from_motion and len(self._motion_x) >= self.min_fits

    def _motion_x_deg(self) -> np.ndarray:
        return np.degrees(np.arcsin(np.clip(np.asarray(self._motion_x), -1.0, 1.0)))

    def _fits_deg(self) -> np.ndarray:
        return np.degrees(np.arcsin(np.clip(np.asarray(self._xy), -1.0, 1.0))).reshape(-1, 2)

    def add(self, normal_base: np.ndarray) -> None:
        n = np.asarray(normal_base, float)
        n = n / np.linalg.norm(n)
        self._xy.append((float(n[0]), float(n[1])))
        self._normal = None

    @property
    def ready(self) -> bool:
        return len(self._xy) >= self.min_fits or self._motion_ready()

    @property
    def normal(self) -> np.ndarray:
        """Unit normal of the floor in the base frame (pointing up): the median of the fits (the base z
        axis before any); with the motion's tilt (``from_motion``, once ready) its x from the motion and its y
        from the fits once they are ready (0 before)."""
        if self._motion_ready():
            if self._normal is None:
                x = float(np.median(np.asarray(self._motion_x)[-MOTION_WINDOW_STEPS:]))
                y = float(np.median(np.asarray(self._xy)[:, 1])) if len(self._xy) >= self.min_fits else 0.0
                self._normal = np.array([x, y, np.sqrt(max(1.0 - x * x - y * y, 0.0))])
            return self._normal.copy()
        if not self._xy:
            return np.array([0.0, 0.0, 1.0])
        if self._normal is None:
            self._normal = self._fits_normal()
        return self._normal.copy()

    def _fits_normal(self) -> np.ndarray:
        x, y = np.median(np.asarray(self._xy), axis=0)
        return np.array([x, y, np.sqrt(max(1.0 - x * x - y * y, 0.0))])

    def standard_error_deg(self) -> float:
        """Standard error of the learnt tilt (deg): the median's, 1.25 sigma / sqrt(n_eff), with the fits' sigma
        from their median absolute deviation (a ramp's few fits do not inflate it).

        Consecutive keyframes' fits share most of the window's floor points, so their errors are correlated and
        n fits are not n measurements: ``n_eff`` is the AR(1) effective sample size n (1 - r) / (1 + r), r the
        lag-1 autocorrelation of the fits (each axis; the smaller n_eff). Counted as independent, 10 fits made a
        0.3-0.8 deg bias of a first stretch look like a significant mount error (a rendered loop and warehouse
        whose mount is exact switched at keyframes 12-13)."""
        if self._motion_ready():
            se_y = _median_and_se(self._fits_deg()[:, 1])[1] if len(self._xy) >= self.min_fits else 0.0
            return float(np.hypot(_median_and_se(self._motion_x_deg())[1], se_y))
        if len(self._xy) < 2:
            return float("inf")
        return _median_and_se(self._fits_deg())[1]

    def significant(self) -> bool:
        """Whether the learnt tilt says the mount is off: ready, ``tilt_significant``, and constant. A mount
        error is constant, the base's rocking and the first keyframes' poorly triangulated floors are not: the
        older and the newer half of the fits must each show a significant tilt, and the same one (within three
        of their combined standard errors)."""
        if self._motion_ready() and _significant_throughout(self._motion_x_deg()):
            return True
        return self._fits_significant()

    def _fits_significant(self) -> bool:
        """``significant`` from the plane fits alone."""
        if len(self._xy) < self.min_fits:
            return False
        xy = self._fits_deg()
        if not tilt_significant(float(np.hypot(*_tilt_deg_of(self._fits_normal()))), _median_and_se(xy)[1]):
            return False
        halves = [_median_and_se(h) for h in (xy[: len(xy) // 2], xy[len(xy) // 2:])]
        (m0, se0), (m1, se1) = halves
        return (all(tilt_significant(float(np.hypot(*m)), se) for m, se in halves)
                and float(np.hypot(*(m1 - m0))) <= 3.0 * float(np.hypot(se0, se1)))

    def tilt_deg(self) -> tuple[float, float]:
        """The normal's tilt toward the base's +x (forward) and +y (left), in degrees."""
        return _tilt_deg_of(self.normal)


def _tilt_deg_of(n: np.ndarray) -> tuple[float, float]:
    """A floor normal's tilt toward the base's +x and +y (deg)."""
    return float(np.degrees(np.arctan2(n[0], n[2]))), float(np.degrees(np.arctan2(n[1], n[2])))


def _median_and_se(xy_deg: np.ndarray) -> tuple[np.ndarray, float]:
    """The median tilt (deg) of some fits, per axis (``(n, 2)``: x and y; ``(n,)``: one axis), and its standard
    error (as ``FloorAttitude.standard_error_deg``; over both axes for two)."""
    if len(xy_deg) < 2:
        return (np.median(xy_deg, axis=0) if len(xy_deg) else np.zeros(np.shape(xy_deg)[1:])), float("inf")
    sigma = 1.4826 * np.median(np.abs(xy_deg - np.median(xy_deg, axis=0)), axis=0)
    spread = np.hypot(*sigma) if np.ndim(sigma) else abs(sigma)
    return np.median(xy_deg, axis=0), float(1.2533 * spread / np.sqrt(effective_sample_size(xy_deg)))


def _significant_throughout(deg: np.ndarray) -> bool:
    """One axis's tilt series is significant as a whole and in each half, with one sign (it may change in size:
    the motion's tilt follows the body's pitch on its suspension as well as the mount's)."""
    m, se = _median_and_se(deg)  # deg: (n,), one axis
    if not tilt_significant(float(abs(m)), se):
        return False
    halves = [_median_and_se(h) for h in (deg[: len(deg) // 2], deg[len(deg) // 2:])]
    return all(tilt_significant(float(abs(mh)), seh) and np.sign(mh) == np.sign(m) for mh, seh in halves)


def effective_sample_size(series: np.ndarray) -> float:
    """AR(1) effective number of independent samples of a (n,) or (n, d) series: n (1 - r) / (1 + r) with r its
    lag-1 autocorrelation (clipped to [0, 0.95]; the smallest over the columns), at least 1."""
    x = np.asarray(series, float).reshape(len(series), -1)
    n = len(x)
    if n < 3:
        return float(n)
    d = x - x.mean(axis=0)
    var = np.sum(d * d, axis=0)
    r = np.where(var > 0, np.sum(d[1:] * d[:-1], axis=0) / np.where(var > 0, var, 1.0), 0.0)
    r = np.clip(r, 0.0, 0.95)
    return float(max(1.0, np.min(n * (1.0 - r) / (1.0 + r))))


def normal_from_tilt_deg(tilt_x_deg: float, tilt_y_deg: float) -> np.ndarray:
    """The floor normal whose tilt toward the base's +x and +y is given (the inverse of
    ``FloorAttitude.tilt_deg``)."""
    n = np.array([np.tan(np.radians(tilt_x_deg)), np.tan(np.radians(tilt_y_deg)), 1.0])
    return n / np.linalg.norm(n)


def levelled_mount(T_base_cam: np.ndarray, normal_base: np.ndarray) -> np.ndarray:
    """``T_base_cam`` with its rotation corrected so that a floor whose normal the camera saw as
    ``normal_base`` (in the base frame ``T_base_cam`` defines) is the base's xy plane.

    A mount pitched or rolled against its calibration rotates the camera, not its position: the true
    rotation is the smallest rotation taking ``normal_base`` to z, applied on the base side; the
    translation stays. What a user puts into ``camera.yaml`` once a run learnt the floor's tilt."""
    n = np.asarray(normal_base, float)
    n = n / np.linalg.norm(n)
    axis = np.cross(n, [0.0, 0.0, 1.0])
    s = float(np.linalg.norm(axis))
    angle = float(np.arctan2(s, n[2]))
    R_fix = so3_exp(axis / s * angle) if angle > 1e-12 else np.eye(3)
    T = np.array(T_base_cam, float, copy=True)
    T[:3, :3] = R_fix @ T[:3, :3]
    return T
