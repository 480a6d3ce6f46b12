"""The back end's floor model: all floor state and the floor's part of each keyframe (``FloorModel``).

The smoother (``smoother.py``) asks it, at each keyframe, which new landmarks lie on the floor (``floor_of``:
a plane fitted over the window's landmarks with ``ground.floor_mask``; after a monocular run's scale drifted,
``_floor_after_scale_drift``), which floor they are tied to (the keyframe's base frame; a level frame when the
base rocks, ``level_up``; a learnt mount tilt with ``ground.mount_calibration``, ``judge_mount`` and
``floor_normal_base``; with ``ground.mount_from_motion`` its pitch from the base's steps, ``observe_motion``), and for the ground factors themselves (``birth_ground_factor``; at the mount switch
``retie_window_floor``; off-floor landmarks lose theirs, ``untie_off_floor``). A monocular run takes its metric
scale from the floor: at its start (``first_baseline``) or when the floor first comes into view
(``late_metric_start``). With ``ground.floor_state`` a keyframe's floor points are tied to a floor frame ``F(k)``
of its own (``add_floor_frame``, ``floor_pose_key``) instead of its base pose; with ``ground.height_sigma_fraction``
that frame is the base pose dropped by the floor's depth, a state shared by the keyframes (``floor_depth.py``). The pure geometry (plane fits, attitude, off-floor test) is in ``ground.py``.

The model reads the window's landmarks (``LandmarkManager``) and keyframe poses; it never touches the
smoother: it adds factors to the update the smoother builds and returns factor indices to remove.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

import gtsam
import numpy as np

from ..camera import CameraModel
from ..config import BackendConfig, MountCalibration
from ..geometry import inv_T, make_T
from ..types import FrontendOutput
from . import factors as fac
from .cue_check import CueAgreement, CueCheck
from .factors import F, X
from .floor_depth import FloorDepthStates
from .ground import (
    FloorAttitude,
    PlaneFit,
    attitude_jitter_deg,
    camera_height_up_to_scale,
    floor_landmarks_to_untie,
    floor_mask,
    level_up,
    range_sigmas_m,
)
from .landmarks import LandmarkManager, triangulate_midpoint

log = logging.getLogger(__name__)

# A monocular run trusts a floor plane it cannot check against a metric height (at its late metric start,
# and after its scale drifted) only when two consecutive keyframes' planes agree within this share (one
# plane could be a table top): ``floors_agree``.
FLOOR_AGREEMENT = 0.1
# Smallest camera height (m) for which the ground cue makes sense.
MIN_CAMERA_HEIGHT_M = 0.05
# A keyframe step's direction tells the floor's tilt (``observe_motion``) only with this much parallax
# (rotation taken out, pixels): below it the two-view direction is noise.
MOTION_MIN_PARALLAX_PX = 2.5
# Keyframes of the window needed before the base's rocking is judged (a median over fewer is noise).
MIN_ROCKING_KEYFRAMES = 5


def observe_motion(attitude: FloorAttitude, fo: FrontendOutput, T_base_cam: np.ndarray) -> None:
    """``ground.mount_from_motion``: a keyframe's step from the last keyframe, as the front end's two-view geometry
    measured it (vision alone), as evidence of the floor's tilt (``FloorAttitude.add_motion``)."""
    if (not attitude.from_motion or not fo.vision_ok or fo.t_dir_kf is None or fo.R_cam_kf_cam is None
            or fo.rot_comp_parallax_px < MOTION_MIN_PARALLAX_PX):
        return
    c_kf = -fo.R_cam_kf_cam.T @ fo.t_dir_kf  # the camera's displacement in the last keyframe's camera frame
    attitude.add_motion(T_base_cam[:3, :3] @ c_kf)


# A monocular first baseline measured by the floor's region (``RoadRegion.first_baseline``): keyframe 1's image, its
# mask, its camera in keyframe 0's base frame -> the camera's step (m), or None
RegionBaseline = Callable[[np.ndarray | None, np.ndarray | None, np.ndarray], float | None]


def first_camera(T_base_cam: np.ndarray, fo: FrontendOutput, t_unit: np.ndarray) -> np.ndarray:
    """Keyframe 1's camera in keyframe 0's base frame from the two views' rotation and unit direction."""
    assert fo.R_cam_kf_cam is not None
    return T_base_cam @ inv_T(make_T(fo.R_cam_kf_cam, t_unit))


def floors_agree(previous: float, current: float) -> bool:
    """Two consecutive keyframes' up-to-scale floor planes (scales or heights) agree within ``FLOOR_AGREEMENT``."""
    return abs(current / previous - 1.0) <= FLOOR_AGREEMENT


class FloorModel:
    """Where the floor is, which landmarks are tied to it, and what scale it gives (the ground cue)."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig, use_odometry: bool, lm: LandmarkManager,
                 kf_pose: dict[int, np.ndarray]):
        self.camera = camera
        self.cfg = cfg
        self.use_odometry = use_odometry
        self.lm = lm  # the window's landmarks (shared with the smoother)
        self.kf_pose = kf_pose  # the window's keyframe poses T_world_base (the smoother's; read here)
        self.T_base_cam = camera.T_base_cam
        # The camera's height above the floor, and where the floor is in the base frame.
        g = cfg.ground
        cam_z = float(self.T_base_cam[2, 3])
        self.camera_height_m = float(g.camera_height_m) if g.camera_height_m is not None else cam_z
        self.floor_z = cam_z - self.camera_height_m  # the floor's z in the base frame
        self.use_ground = g.enabled and self.camera_height_m >= MIN_CAMERA_HEIGHT_M
        if g.enabled and not self.use_ground:
            log.warning("ground cue off: camera height %.3f m above the floor is too small (T_base_cam z, "
                        "or backend.ground.camera_height_m)", self.camera_height_m)
        self.ground_sigma_m = g.sigma_height_fraction * self.camera_height_m  # one floor point's own error
        # The error a keyframe's floor points share (its floor's height under the camera), None: independent.
        self.common_sigma_m = (None if g.sigma_common_fraction is None
                               else g.sigma_common_fraction * self.camera_height_m)
        self._rng = np.random.default_rng(g.seed)
        # The floor's attitude in the base frame is always learnt (the summary reports it: a tilted mount
        # shows there); with ground.mount_calibration it is also used.
        self.floor_attitude = FloorAttitude(g.mount_min_fits, g.mount_fits, g.mount_from_motion)
        # ground.mount_calibration auto: the learnt normal is used from the first keyframe where its tilt is
        # significant on (sticky).
        self.mount_normal_used = g.mount_calibration is MountCalibration.ON
        self.retie_pending = False  # the window's floor landmarks are re-tied at the next update
        # ground.floor_state: the keyframes with a floor frame F(k) in the smoother (their floor points tie to it).
        self.floor_frames: set[int] = set()
        # ground.height_sigma_fraction: the floor's depth below its configured height, a state shared by the keyframes.
        self.depth = FloorDepthStates(cfg, self.camera_height_m)
        self.floor_normal_learnt = False  # the last update measured its floor points along the learnt normal
        # How well the floor's attitude against the base is known (ground.sigma_tilt_deg): far points' heights.
        self.tilt_sigma_rad = float(np.radians(g.sigma_tilt_deg))
        # Metric scale: from the wheels, or (monocular) once the ground plane has fixed the first baseline, or
        # later, when the floor first comes into view (``late_metric_start``).
        self.metric = use_odometry
        self.metric_from_keyframe: int | None = None  # a late metric start: the keyframe it happened at
        self._late_scale: float | None = None  # the last keyframe's floor scale while waiting for one
        # Monocular, metric: the height of the last keyframe's floor plane at a drifted scale (None: the metric
        # fit passed or no plane), and how often the floor was taken back at one (``_floor_after_scale_drift``).
        self._drift_height: float | None = None
        self.n_scale_reanchors = 0
        self.n_ground_factors = 0
        self.n_floor_untied = 0  # ground factors removed from floor landmarks found off the floor (``untie_off_floor``)
        self.n_floor_beside_track = 0  # of them, beside the track the base drove (``ground.corridor_heights``)
        self.n_level_ground_factors = 0  # of them, measured along the floor's normal (the base rocks)
        self.base_rocking_deg = float("nan")  # attitude_jitter_deg over the window at the last floor fit
        self.level_frame = False  # the last update measured its floor points in the level frame
        self.n_ground_keyframes = 0
        # Floor against wheels (``check_cues``): this update's floor plane height (in the estimate) and the test.
        self.fit_height_m: float | None = None
        wc = cfg.wheel_calibration
        self.cues = (CueCheck(cfg.cue_check, self.camera_height_m, wc.scale_prior_sigma,
                              g.sigma_common_fraction or g.sigma_height_fraction)
                     if use_odometry and self.use_ground and cfg.cue_check.enabled else None)
        self.last_agreement: CueAgreement | None = None

    # ------------------------------------------------------------------ state
    def ground_active(self) -> bool:
        return self.use_ground and self.metric

    def waiting_for_floor(self) -> bool:
        """A monocular run that saw no floor at its start: up to scale until ``late_metric_start``."""
        return self.use_ground and not self.metric

    def begin_update(self) -> None:
        """A new update: nothing measured in the level frame or along the learnt normal yet, no floor plane."""
        self.level_frame = self.floor_normal_learnt = False
        self.fit_height_m = None
        self.last_agreement = None

    def ties_allowed(self) -> bool:
        """New floor points are tied to the floor: it has a metric height and, with wheels, floor and wheels were
        tested and agree (``CueCheck.floor_gated``)."""
        return not self.waiting_for_floor() and not (self.cues is not None and self.cues.floor_gated())

    def check_cues(self, k: int, wheel_m: float | None, estimate_m: float, road_height_m: float | None = None) -> None:
        """Keyframe k's test of floor against wheels (``cue_check.py``) after its update; logs when a disagreement
        starts and ends. ``road_height_m``: the camera height the region implies where no plane was fitted."""
        if self.cues is None or not self.ground_active():
            return
        was_gated, first = self.cues.floor_gated(), not self.cues.tests
        height = self.fit_height_m if self.fit_height_m is not None else road_height_m
        self.last_agreement = a = self.cues.observe(k, wheel_m, estimate_m, height)
        if a is None:
            return
        if not a.agree and self.cues.disagree_since == k:
            log.warning("keyframe %d: floor and wheels disagree on the scale by %+.1f%% (chi-square %.1f > %.1f)%s",
                        k, 100.0 * a.disagreement, a.chi2, self.cues.threshold,
                        ": floor points are not tied to the floor while they do" if self.cfg.cue_check.gate else "")
        elif was_gated and a.agree:
            log.info("keyframe %d: floor and wheels agree %s (%+.1f%%)", k, "at their first test" if first else "again",
                     100.0 * a.disagreement)

    def count_ground_factors(self, n_ground: int) -> None:
        """An update's ground factors went into the smoother."""
        self.n_ground_factors += n_ground
        self.n_ground_keyframes += int(n_ground > 0)

    def floor_offset(self, n_base: np.ndarray | None) -> float:
        """The floor as the plane ``n_base . q = offset`` in the base frame: the camera at its known height
        above it (with the base z axis: the floor's z, 0 unless the camera height is overridden)."""
        if n_base is None:
            return self.floor_z
        return float(n_base @ self.T_base_cam[:3, 3]) - self.camera_height_m

    def floor_normal_base(self) -> np.ndarray | None:
        """The floor's normal in the base frame learnt so far, when it is used (None: the base z axis)."""
        if not self.mount_normal_used or not self.floor_attitude.ready:
            return None
        return self.floor_attitude.normal

    # ------------------------------------------------------------------ which landmarks are floor
    def below_horizon(self, tids: list[int], T_guess: np.ndarray) -> np.ndarray:
        """Whether each track's newest ray points below the horizon (a cheap floor pre-check)."""
        if not tids:
            return np.zeros(0, bool)
        uv = np.asarray([self.lm.obs[t][-1][1] for t in tids])
        K = self.camera
        rays = np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(uv))], axis=1)
        d = rays @ self.T_base_cam[:3, :3].T
        dep = np.degrees(np.arctan2(-d[:, 2], np.hypot(d[:, 0], d[:, 1])))
        return dep >= self.cfg.ground.min_depression_deg

    def floor_of(self, k: int, born: list[tuple[int, np.ndarray]], T_guess: np.ndarray
                 ) -> tuple[np.ndarray, PlaneFit | None]:
        """Which new landmarks (of keyframe k) lie on the floor (plane fitted over the window's landmarks and
        them), and the plane (base frame of ``T_guess``).

        On a level base the ground factor takes the base's own xy plane as the floor (a rocking one:
        ``level_up``). Measured against it: a normal
        refitted per keyframe was noisier than the base attitude the smoother estimates from all the
        evidence, and a mean of the last 30 keyframes' normals (for a camera pitched on its mount) took
        up a ramp's tilt ahead (rendered ramp 0.012 -> 0.051 m) without helping on KITTI."""
        if self.waiting_for_floor() and born:
            # No metric height to fit a floor plane at yet: below the horizon is all that is known.
            return self.below_horizon([tid for tid, _ in born], T_guess), None
        if not self.ground_active() or not born:
            return np.zeros(len(born), bool), None
        new_pts = np.asarray([p for _, p in born])
        old_pts = self.lm.positions()[1]
        pts = np.concatenate([new_pts, old_pts])
        mask, fit = floor_mask(pts, T_guess, self.T_base_cam, self.camera_height_m, self.cfg.ground, self._rng)
        if fit is None and not self.use_odometry and self.cfg.ground.reanchor_drifted_floor:
            mask, fit = self._floor_after_scale_drift(k, pts, T_guess)
        else:
            self._drift_height = None
        fa = self.floor_attitude
        if fit is not None:
            self.fit_height_m = fit.camera_height_m
            fa.add(fit.normal)
            if self.cfg.ground.mount_calibration is MountCalibration.ON and not fa.ready:
                # Still learning the floor's attitude on the mount: floor points tied to a floor the mount
                # may be tilted against would set a wrong scale (and the wheel calibration with it), which
                # the calibration's slow random walk then carries for the rest of the run.
                return np.zeros(len(born), bool), fit
        return mask[: len(born)], fit

    def _floor_after_scale_drift(self, k: int, pts: np.ndarray, T_guess: np.ndarray
                                 ) -> tuple[np.ndarray, PlaneFit | None]:
        """The floor of a monocular run whose scale drifted (no wheels: the floor is its only scale source).

        While no floor is in view the scale drifts like any monocular run's (KITTI 01 on the highway: 35%
        in 7 keyframes without floor tracks); when the floor is back, it lies at a height the metric fit
        rejects (``height_tolerance``), and the run would stay drifted. A plane found at the same height at
        two consecutive keyframes (``floors_agree``, as at the late metric start: one plane could be a
        table top) is taken as the floor again: its ground factors pull the scale back."""
        mask, fit = floor_mask(pts, T_guess, self.T_base_cam, self.camera_height_m, self.cfg.ground, self._rng,
                               metric_scale_known=False)
        prev, self._drift_height = self._drift_height, (None if fit is None else fit.camera_height_m)
        if fit is None or prev is None or not floors_agree(prev, fit.camera_height_m):
            return np.zeros(len(pts), bool), None
        self.n_scale_reanchors += 1
        log.info("keyframe %d: the floor is back, %.2f x the camera height below the camera (the scale drifted "
                 "while it was out of view); tied to it again", k, fit.camera_height_m / self.camera_height_m)
        return mask, fit

    # ------------------------------------------------------------------ which floor they are tied to
    def judge_mount(self, k: int) -> bool:
        """``ground.mount_calibration`` auto: switch to the learnt floor normal once its tilt is significant.
        Returns whether it switched at keyframe k.

        Until then the floor points were tied to the base's xy plane, which a tilted mount makes the wrong
        floor. So at the switch the window's floor landmarks are re-tied along the learnt normal
        (``retie_window_floor``). Measured on loops whose camera.yaml is 0.5 / 1 / -1 deg off: 0.13-0.26 m ->
        0.010-0.021 m (docs/performance.md, mount study). The wheel calibration's scale is not released at the
        switch (it was until stop 58: no measurable effect on 23 sequences, docs/scale_suite.md)."""
        if (self.cfg.ground.mount_calibration is not MountCalibration.AUTO or self.mount_normal_used
                or not self.floor_attitude.significant()):
            return False
        self.mount_normal_used = self.retie_pending = True
        tx, ty = self.floor_attitude.tilt_deg()
        log.warning("keyframe %d: the floor is tilted %.2f deg in the base frame (T_base_cam's pitch or roll looks "
                    "off by that): floor heights are measured along the learnt normal from here on", k,
                    float(np.hypot(tx, ty)))
        return True

    def level_up(self, k: int, w0: int, T_guess: np.ndarray, fit: PlaneFit | None) -> np.ndarray | None:
        """The floor's normal (world) to measure keyframe k's floor points along when the base rocks,
        else None (the native factor in the keyframe's own base frame); ``w0`` is the window's start.

        Measured on 20 rendered sequences rocking by 0.7-2 deg (docs/performance.md): ATE 0.42x-1.71x of
        the native factor's, geometric mean 0.87x; wheel scale 0.02-0.59% off (mean 0.22%) instead of
        0.02-0.82% (mean 0.32%). Level runs and the ramp never reach ``ground.rocking_jitter_deg``, so
        they keep the native factor, which also holds each keyframe's attitude to the floor (the level
        frame everywhere cost them 1.07x on average over ten seeds, the ramp 1.25x)."""
        g = self.cfg.ground
        Rs = [self.kf_pose[kk][:3, :3] for kk in range(w0, k) if kk in self.kf_pose]
        z_axes = np.array([R[:, 2] for R in Rs]).reshape(-1, 3)
        self.base_rocking_deg = attitude_jitter_deg(z_axes) if len(z_axes) >= MIN_ROCKING_KEYFRAMES else float("nan")
        if (g.rocking_jitter_deg is None or fit is None or not self.base_rocking_deg > g.rocking_jitter_deg
                or g.floor_state):  # a floor frame of its own takes the rocking up
            return None
        if self.n_level_ground_factors == 0:
            log.info("keyframe %d: the base rocks (median tilt change %.2f deg between keyframes): floor points "
                     "are measured along the floor's normal while it does", k, self.base_rocking_deg)
        n_base = self.floor_normal_base()
        floor_normals = z_axes if n_base is None else np.array([R @ n_base for R in Rs])
        return level_up(floor_normals, T_guess[:3, :3] @ fit.normal, g.level_select_deg)

    # ------------------------------------------------------------------ ground factors
    def floor_pose_key(self, k: int) -> int:
        """The pose keyframe k's floor points are tied in: its floor frame F(k) (``ground.floor_state``), else
        its base pose X(k)."""
        return F(k) if k in self.floor_frames else X(k)

    def add_floor_frame(self, k: int, graph, values, stamps: dict[int, float], owners: list,
                        T_guess: np.ndarray) -> None:
        """Keyframe k's floor frame F(k), with its factor to X(k) (``ground.floor_state``; or, with
        ``ground.height_sigma_fraction``, X(k) dropped by the shared floor depth, whose chain starts here if it is
        not live); once per keyframe, in the update that first ties floor points at k; stamped as X(k), so both
        leave the window together."""
        g = self.cfg.ground
        if not (g.floor_state or self.depth.wanted) or k in self.floor_frames:
            return
        if g.floor_state:
            values.insert(F(k), gtsam.Pose3(T_guess))
            graph.add(fac.floor_frame_factor(k, float(np.radians(g.floor_tilt_sigma_deg)),
                                             g.floor_height_fraction * self.camera_height_m))
        else:  # ground.height_sigma_fraction: F(k) is X(k) dropped by the shared floor depth
            n_before = graph.size()
            depth_key = self.depth.start(graph, values, stamps, k, T_guess)
            owners.extend([None] * (graph.size() - n_before))
            values.insert(F(k), gtsam.Pose3(T_guess @ make_T(np.eye(3), np.array([0.0, 0.0, -self.depth.depth_m]))))
            graph.add(fac.floor_depth_factor(k, depth_key))
        stamps[F(k)] = float(k)
        owners.append(None)
        self.floor_frames.add(k)

    def point_sigma_m(self, n_points: int) -> float:
        """The height sigma of each of the ``n_points`` floor points one keyframe ties to its floor.

        A point's height off the floor has its own error (triangulation, ``sigma_height_fraction``) and one
        that all of the keyframe's floor points share (``sigma_common_fraction``: the floor's height under the
        camera there varies with the suspension, the tyres, the local surface). Their mean then knows the
        height to ``sqrt(s_own^2 / n + s_common^2)``, never better than ``s_common``; the same information
        spread evenly over the n factors gives each ``sqrt(s_own^2 + n s_common^2)``. Independent factors of
        sigma ``s_own`` would claim ``s_own / sqrt(n)``: 100 points a height known to 0.3% of itself, which
        a road's kerbs and grass a few centimetres above the asphalt do not allow."""
        if self.common_sigma_m is None:
            return self.ground_sigma_m
        return float(np.sqrt(self.ground_sigma_m**2 + max(n_points, 1) * self.common_sigma_m**2))

    def birth_ground_factor(self, k: int, key: int, p_world: np.ndarray, T_guess: np.ndarray,
                            up_world: np.ndarray | None, n_base: np.ndarray | None, n_points: int = 1):
        """A new floor landmark's ground factor at its birth keyframe k: along the base's z axis (or the
        learnt floor normal ``n_base``) natively, or along the level frame's up when the base rocks;
        ``n_points``: the floor points keyframe k ties (``point_sigma_m``)."""
        cfg = self.cfg
        self.floor_normal_learnt = n_base is not None
        p_base = (p_world - T_guess[:3, 3]) @ T_guess[:3, :3]
        sigma, outlier_sigma = self.range_sigmas_m(self.point_sigma_m(n_points), p_base)
        if up_world is not None:
            self.n_level_ground_factors += 1
            self.level_frame = True
            # The shared depth's floor frame is X(k) dropped along its z axis: its floor too. floor_state's frames tilt
            # against X(k), which the level frame does not measure.
            pose_key = self.floor_pose_key(k) if self.depth.wanted else X(k)
            return fac.level_ground_factor(pose_key, key, up_world, self.floor_z, sigma, cfg, outlier_sigma)
        return fac.ground_factor(self.floor_pose_key(k), key, p_base, self.floor_offset(n_base), sigma, cfg, n_base,
                                 outlier_sigma)

    def range_sigmas_m(self, sigma_m: float, p_base: np.ndarray) -> tuple[float, float]:
        """A floor point's sigma and its robust threshold's, widened at its range by ``ground.sigma_tilt_deg``."""
        return range_sigmas_m(sigma_m, self.ground_sigma_m, p_base, self.tilt_sigma_rad)

    def retie_window_floor(self, k: int, w0: int, graph, owners: list) -> list[int]:
        """Tie the window's floor landmarks to the floor along the learnt normal instead of the base z axis
        (at the switch of ``judge_mount``): their ground factors are replaced, so the keyframes still in
        the window lose the scale the wrong floor gave them. Returns the factor indices to remove."""
        self.retie_pending = False
        n_base = self.floor_normal_base()
        offset = self.floor_offset(n_base)
        removed = []
        tied = self.lm.tied_to_floor(w0)
        per_keyframe = Counter(kk for _, kk, _, _ in tied)
        for tid, kk, fi, p_world in tied:
            T = self.kf_pose[kk]
            p_base = (p_world - T[:3, 3]) @ T[:3, :3]
            key = self.lm.landmarks[tid].key
            sigma, outlier_sigma = self.range_sigmas_m(self.point_sigma_m(per_keyframe[kk]), p_base)
            graph.add(fac.ground_factor(self.floor_pose_key(kk), key, p_base, offset, sigma, self.cfg, n_base,
                                        outlier_sigma))
            owners.append((tid, kk, True))
            self.lm.drop_factor(tid, kk, fi)
            removed.append(fi)
        log.info("keyframe %d: %d floor landmarks of the window re-tied along the learnt normal", k, len(removed))
        return removed

    def untie_off_floor(self, w0: int) -> None:
        """Remove (at the next update) the ground factors of the window's floor landmarks whose height above the
        floor of the keyframe that tied them, in the new estimate, strays from the others' (``ground.off_floor``).

        With ``ground.corridor_heights``, also those the base has driven past beside its track (``beside_track``).
        Only native ground factors (``lm.ground_factor``); the level frame's, on a rocking base, are left alone.
        Measured (docs/performance.md): a loop lined with 3 cm kerbs, wheels +2%: ATE SE(3) 0.041 -> 0.017 m
        (without wheels 0.097 -> 0.023 m); 19 plain loops and figure eights 0.94x-1.31x, geometric mean 1.04."""
        self.floor_frames = {kk for kk in self.floor_frames if kk >= w0}
        g = self.cfg.ground
        tied = self.lm.tied_to_floor(w0) if g.untie_sigmas is not None or g.corridor_heights is not None else []
        if not tied:
            return
        n_base = self.floor_normal_base()
        track_world = np.array([self.kf_pose[kk][:3, 3] for kk in sorted(self.kf_pose) if kk >= w0])
        off, beside = floor_landmarks_to_untie(np.stack([self.kf_pose[kk] for _, kk, _, _ in tied]),
                                               np.stack([p_world for *_, p_world in tied]), n_base,
                                               self.floor_offset(n_base), track_world, g, self.camera_height_m)
        self.n_floor_beside_track += int(np.count_nonzero(beside))
        for (tid, kk, fi, _), is_off in zip(tied, off):
            if is_off:
                self.lm.drop_factor(tid, kk, fi)
                self.lm.pending_removal.append(fi)
                self.n_floor_untied += 1

    # ------------------------------------------------------------------ metric scale (monocular)
    def first_baseline(self, fo: FrontendOutput, t_unit: np.ndarray, region: RegionBaseline | None = None
                       ) -> float | None:
        """The monocular start's first baseline that puts the floor at the camera's known height (the run is metric
        from here), or None (no floor plane in the first two keyframes: up to scale for now). ``region``: where the
        corners give no plane, the floor's region measures it (``RoadRegion.first_baseline``)."""
        baseline, source = self._two_view_ground_baseline(fo, t_unit) if self.use_ground else None, "plane"
        if baseline is None and self.use_ground and region is not None:
            baseline, source = region(fo.image, fo.image_mask, first_camera(self.T_base_cam, fo, t_unit)), "region"
        if baseline is not None:
            self.metric = True
            log.info("monocular start: the floor %s sets the first baseline to %.3f m (metric)", source, baseline)
        elif self.use_ground:
            log.warning("monocular start: no floor plane in the first two keyframes yet; up to scale until the floor "
                        "comes into view (from there metric, the trajectory before it rescaled)")
        return baseline

    def _two_view_ground_baseline(self, fo: FrontendOutput, t_unit: np.ndarray) -> float | None:
        """Length of the first baseline that puts the floor at the camera's known height."""
        # Both keyframes in a unit-baseline world anchored at keyframe 0's base.
        T_b0_c1 = first_camera(self.T_base_cam, fo, t_unit)
        cams = LandmarkManager.camera_poses({0: np.eye(4)}, self.T_base_cam)
        cams[1] = (T_b0_c1[:3, :3], T_b0_c1[:3, 3])
        cur = dict(zip(fo.track_ids.tolist(), fo.pixels_undistorted))
        cos_min = float(np.cos(np.radians(self.cfg.min_triangulation_angle_deg)))
        pts = []
        for tid, lst in self.lm.obs.items():
            first = [p for kk, p, _ in lst if kk == 0]
            if first and tid in cur:
                p = triangulate_midpoint(self.camera, self.cfg.model_copy(update={"max_landmark_depth_m": 1e6}),
                                         [(0, first[0]), (1, cur[tid])], cams, cos_min)
                if p is not None:
                    pts.append(p)
        if len(pts) < self.cfg.ground.min_points:
            return None
        # Keyframe 0's base is the world: around the camera centre, the points are in the base's orientation.
        height = camera_height_up_to_scale(np.asarray(pts) - self.T_base_cam[:3, 3], self.cfg.ground, self._rng)
        return None if height is None else self.camera_height_m / height

    def _floor_scale_now(self, k: int) -> float | None:
        """Up to scale: the factor that would put the floor plane under the window's landmarks at the camera's
        known height (None: no floor plane in view), as at the monocular start, with a refining second fit."""
        _, pts = self.lm.positions()
        T_wb = self.kf_pose[k]
        rel = (pts - (T_wb @ self.T_base_cam)[:3, 3]) @ T_wb[:3, :3]
        height = camera_height_up_to_scale(rel, self.cfg.ground, self._rng, refine=True)
        return None if height is None else self.camera_height_m / height

    def late_metric_start(self, k: int) -> float | None:
        """A monocular run with no floor in its first two keyframes is up to scale until the floor comes into
        view. When two consecutive keyframes' floor planes agree on the scale, the run is metric from keyframe k
        on: returns the factor to rescale the trajectory so far by (None: the run stays up to scale)."""
        scale = self._floor_scale_now(k)
        prev, self._late_scale = self._late_scale, scale
        if scale is None or prev is None or not floors_agree(prev, scale):
            return None
        self.metric, self.metric_from_keyframe = True, k
        return float(np.sqrt(scale * prev))
