"""The back end's window: keys, timestamps, iSAM2 (GTSAM's fixed-lag smoother), reset.

``SlidingWindowBackend.add_keyframe`` takes one keyframe's tracks and wheel step, asks the
factor builders (``factors.py``) for factors, the landmark manager (``landmarks.py``) for
landmarks, the ground cue (``ground.py``) for floor landmarks and the floor they are tied to (the
keyframe's base frame; a level frame when the base rocks, ``_level_up``; a learnt mount tilt with
``ground.mount_calibration``, ``floor_normal_base``), and submits one update. ``_update`` builds it
in steps, one method each: the pose and its motion factors (``_pose_factors``), the observations of
known landmarks (``_observation_factors``), new landmarks with their ground factors
(``_new_landmark_factors``, ``_birth_ground_factor``), the smoother update (``_solve``).

States: ``X(k)`` is ``T_world_base`` of keyframe k, ``L(id)`` the world position of the landmark
of track ``id`` (``G(id)`` for a floor landmark), ``C(k)`` the wheel calibration (distance scale, yaw bias per metre) from keyframe k on,
one per block of keyframes that leave the window together.
The camera enters the projection factors through ``T_base_cam`` (GTSAM's ``body_P_sensor``).

Key lifecycle (designed so that GTSAM's fixed-lag smoother never meets a key it cannot handle,
see GTSAM issues #1638/#1795/#2478/#2741/#1976):

* the smoother's clock is the keyframe counter; before each update the lag is set so that exactly
  the keyframes before ``window_start(k)`` leave (in blocks of ``marginalize_every``);
* every new pose arrives with its timestamp and at least one factor (odometry, or a weak motion
  prior in monocular mode); every new landmark with its timestamp and at least two projection
  factors, all on poses still inside the window; every new calibration state ``C(k)`` with its
  timestamp and a random-walk factor from the previous one (so the chain never breaks, with or
  without a wheel reading at this step), and the wheel factor that uses it;
* a landmark's timestamp is refreshed whenever a new keyframe observes it, so it is
  marginalised together with the last pose that saw it; so is the live calibration state's at
  every keyframe of its block, so it leaves with its block's last pose, and what the old states
  knew about the calibration is carried forward by the marginal on the next state;
* every landmark is born with a weak position prior (sigma about its depth), so a landmark whose
  projection factors are removed as outliers, or lose their Jacobians when the point falls behind
  a camera, is never left undetermined; a floor landmark's ground factor is owned by it and
  removed with its projection factors;
* any remaining failure (indeterminant system, cheirality) resets the window from the last good
  pose (and calibration) with priors and falls back on wheel odometry for that keyframe.
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from ..camera import CameraModel
from ..config import BackendConfig, MountCalibration
from ..errors import WindowVOError
from ..geometry import inv_T, make_T
from ..types import (
    BackendOutput,
    BackendStatus,
    FrontendOutput,
    GateOutcome,
    OdometryStep,
    ScaleSource,
    WheelCalibration,
)
from . import factors as fac
from .factors import C, L, X
from .ground import (
    UNTIE_MIN_SIGMA_HEIGHTS,
    FloorAttitude,
    PlaneFit,
    attitude_jitter_deg,
    camera_height_up_to_scale,
    floor_mask,
    level_up,
    off_floor,
)
from .landmarks import LandmarkManager, reprojection_errors, reprojection_rms, triangulate_midpoint
from .report import ScaleReport, scale_report

log = logging.getLogger(__name__)

__all__ = ["C", "L", "OdometryStep", "SlidingWindowBackend", "X"]

# After a reset the calibration restarts from its last estimate with this share of the prior sigmas.
RESET_CALIBRATION_SIGMA_FACTOR = 0.2
# A monocular run trusts a floor plane it cannot check against a metric height (at its late metric start,
# and after its scale drifted) only when two consecutive keyframes' planes agree within this share (one
# plane could be a table top): ``_floors_agree``.
FLOOR_AGREEMENT = 0.1
# Smallest camera height (m) for which the ground cue makes sense.
MIN_CAMERA_HEIGHT_M = 0.05
# Keyframes of the window needed before the base's rocking is judged (a median over fewer is noise).
MIN_ROCKING_KEYFRAMES = 5


def _floors_agree(previous: float, current: float) -> bool:
    """Two consecutive keyframes' up-to-scale floor planes (scales or heights) agree within ``FLOOR_AGREEMENT``."""
    return abs(current / previous - 1.0) <= FLOOR_AGREEMENT


class SlidingWindowBackend:
    """Fixed-lag smoother fed one keyframe at a time."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig, use_odometry: bool):
        self.camera = camera
        self.cfg = cfg
        self.use_odometry = use_odometry
        self.K = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
        self.T_base_cam = camera.T_base_cam
        self.body_P_sensor = gtsam.Pose3(camera.T_base_cam)
        self.pixel_noise = fac.pixel_noise(cfg)
        self.lag = float(cfg.window_keyframes - 1)
        self.lm = LandmarkManager(camera, cfg)
        # Online calibration starts with the first floor landmarks: before, nothing but the wheels could
        # fix the scale, so a free wheel scale would drift (measured on KITTI, where the road is seldom
        # tracked). ``calibrate`` says whether the calibration states C(k) are live.
        self.calibration_wanted = use_odometry and cfg.wheel_calibration.enabled
        self.calibrate = False
        self.calib_start = -1
        self.calib_key = -1  # keyframe index of the live calibration state C(calib_key)
        self.calib_distance_m = 0.0  # driven since C(calib_key) was created (its random walk)
        self.calib = WheelCalibration()
        # Ground cue: the camera's height above the floor, and where the floor is in the base frame.
        g = cfg.ground
        cam_z = float(self.T_base_cam[2, 3])
        self.camera_height_m = float(g.camera_height_m) if g.camera_height_m is not None else cam_z
        self.floor_z = cam_z - self.camera_height_m  # the floor's z in the base frame
        self.use_ground = g.enabled and self.camera_height_m >= MIN_CAMERA_HEIGHT_M
        if g.enabled and not self.use_ground:
            log.warning("ground cue off: camera height %.3f m above the floor is too small (T_base_cam z, "
                        "or backend.ground.camera_height_m)", self.camera_height_m)
        self.ground_sigma_m = g.sigma_height_fraction * self.camera_height_m
        self._rng = np.random.default_rng(g.seed)
        # The floor's attitude in the base frame is always learnt (the summary reports it: a tilted mount
        # shows there); with ground.mount_calibration it is also used.
        self.floor_attitude = FloorAttitude(g.mount_min_fits, g.mount_fits)
        # ground.mount_calibration auto: the learnt normal is used from the first keyframe where its tilt is
        # significant on (sticky), and the wheel calibration's scale is released once at that keyframe.
        self.mount_normal_used = g.mount_calibration is MountCalibration.ON
        self._release_scale = self._retie_floor = False
        self.floor_normal_learnt = False  # the last update measured its floor points along the learnt normal
        # Metric scale: from the wheels, or (monocular) once the ground plane has fixed the first baseline, or
        # later, when the floor first comes into view (``_late_metric_start``).
        self.metric = use_odometry
        self.metric_from_keyframe: int | None = None  # a late metric start: the keyframe it happened at
        self._late_scale: float | None = None  # the last keyframe's floor scale while waiting for one
        # Monocular, metric: the height of the last keyframe's floor plane at a drifted scale (None: the metric
        # fit passed or no plane), and how often the floor was taken back at one (``_floor_after_scale_drift``).
        self._drift_height: float | None = None
        self.n_scale_reanchors = 0
        self.n_ground_factors = 0
        self.n_floor_untied = 0  # ground factors removed from floor landmarks found off the floor (``_untie_off_floor``)
        self.n_level_ground_factors = 0  # of them, measured along the floor's normal (the base rocks)
        self.base_rocking_deg = float("nan")  # attitude_jitter_deg over the window at the last floor fit
        self.level_frame = False  # the last update measured its floor points in the level frame
        self.n_ground_keyframes = 0
        self.k = -1
        self.kf_frame: dict[int, int] = {}
        self.kf_time: dict[int, float] = {}
        self.kf_pose: dict[int, np.ndarray] = {}  # latest estimate; final once marginalised
        self._estimate: gtsam.Values | None = None
        self.n_resets = 0
        self._new_smoother()

    # ------------------------------------------------------------------ smoother plumbing
    @property
    def estimate(self) -> gtsam.Values | None:
        """The smoother's latest estimate (landmark positions are read from it once, when it is set)."""
        return self._estimate

    @estimate.setter
    def estimate(self, est: gtsam.Values | None) -> None:
        self._estimate = est
        self.lm.read_estimate(est)

    def _new_smoother(self) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(fac.relinearize_thresholds(self.cfg))
        params.relinearizeSkip = self.cfg.relinearize_skip
        # Reuse the slots of removed and marginalised factors: otherwise the factor list grows by
        # every factor ever added, and memory and update time with it.
        params.findUnusedFactorSlots = True
        if self.cfg.optimizer == "dogleg":
            # Powell's dogleg keeps iSAM2's steps inside a trust region: far landmarks with little
            # parallax make plain Gauss-Newton overshoot.
            params.setOptimizationParams(gtsam.ISAM2DoglegParams())
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag, params)

    def window_start(self, k: int | None = None) -> int:
        """Oldest keyframe index in the window after update k.

        Old keyframes leave in blocks of ``marginalize_every`` (B): the start moves only when k is a
        multiple of B, so the window holds ``window_keyframes`` to ``window_keyframes + B - 1``
        keyframes. Measured: marginalisation is most of an update's cost (iSAM2 re-eliminates the
        window and the marginal becomes one dense factor over the landmarks the leaving keyframes saw),
        about 15 ms against 5-9 ms without; in blocks, B - 1 updates in B skip it."""
        k = self.k if k is None else k
        b = self.cfg.marginalize_every
        return max(0, k - k % b - (self.cfg.window_keyframes - 1))

    def pose(self, k: int) -> np.ndarray:
        return self.kf_pose[k]

    def scale_report(self) -> ScaleReport:
        """Whether this run is metric, what fixed its scale, and the final wheel calibration (typed)."""
        return scale_report(self)

    def scale_sources(self) -> list[ScaleSource]:
        """What fixes the metric scale of this run."""
        out = []
        if self.use_odometry:
            out.append(ScaleSource.WHEELS_CALIBRATED if self.calibrate else ScaleSource.WHEELS)
        if self.use_ground and self.n_ground_factors > 0:
            out.append(ScaleSource.GROUND_PLANE)
        return out

    # ------------------------------------------------------------------ main entry
    def add_keyframe(self, fo: FrontendOutput, odom: OdometryStep | None) -> BackendOutput:
        t0 = time.perf_counter()
        self.k += 1
        k = self.k
        self.kf_frame[k] = fo.frame_index
        self.kf_time[k] = fo.timestamp
        status = BackendStatus.OK
        # New landmarks need a vision-worthy keyframe; each one is still checked for its own
        # triangulation angle, so low overall parallax (distant scenes, turning) does not block it.
        allow_new = fo.gate in (GateOutcome.PASS, GateOutcome.LOW_PARALLAX) or k == 1
        T_guess = self._initial_guess(fo, odom)
        n_new = n_vis = n_ground = 0
        earlier: dict[int, np.ndarray] | None = None
        try:
            n_new, n_vis, n_ground = self._update(fo, odom, T_guess, fo.vision_ok, allow_new)
            if k == 0:
                status = BackendStatus.INIT
            elif not fo.vision_ok:
                status = BackendStatus.ODOMETRY_FALLBACK
            elif self._waiting_for_floor() and k >= 2:
                earlier = self._late_metric_start(fo)
        except RuntimeError as err:
            msg = " ".join(str(err).split())[:300]
            log.warning("keyframe %d (frame %d): smoother failed (%s); resetting the window from the last good pose",
                        k, fo.frame_index, msg)
            self._reset_with(fo, odom, T_guess)
            status = BackendStatus.RECOVERED
        out = self._output(fo, n_new, n_vis, n_ground, status)
        if earlier is not None:
            out.metric_start, out.earlier_keyframe_poses = True, earlier
        out.backend_ms = (time.perf_counter() - t0) * 1000.0
        return out

    # ------------------------------------------------------------------ pieces
    def _odometry_usable(self, odom: OdometryStep | None) -> bool:
        return odom is not None and odom.ok and self.use_odometry

    def _initial_guess(self, fo: FrontendOutput, odom: OdometryStep | None) -> np.ndarray:
        k = self.k
        if k == 0:
            return np.eye(4)
        T_prev = self.kf_pose[k - 1]
        if odom is not None and self._odometry_usable(odom):
            return T_prev @ self.calib.correct(odom.T_prev_cur, odom.distance_m)
        T_pnp = self.lm.pnp_pose(fo.track_ids, fo.pixels_undistorted, self.cfg.pixel_sigma)
        if T_pnp is not None:
            return T_pnp
        if k == 1 and fo.R_cam_kf_cam is not None and fo.t_dir_kf is not None:
            # Two-view initialisation: X_cur = R X_kf + t, with a unit baseline, or the metric one the
            # floor gives (camera at its known height).
            t_unit = fo.t_dir_kf / max(np.linalg.norm(fo.t_dir_kf), 1e-9)
            baseline = self._two_view_ground_baseline(fo, t_unit) if self.use_ground else None
            if baseline is not None:
                self.metric = True
                log.info("monocular start: the floor plane sets the first baseline to %.3f m (metric)", baseline)
            elif self.use_ground:
                log.warning("monocular start: no floor plane in the first two keyframes; the run is up to scale until the "
                            "floor comes into view")
            T_cur_kf = make_T(fo.R_cam_kf_cam, t_unit * (baseline or 1.0))
            T_world_cam = T_prev @ self.T_base_cam @ inv_T(T_cur_kf)
            return T_world_cam @ inv_T(self.T_base_cam)
        if k >= 2:  # constant velocity
            d = inv_T(self.kf_pose[k - 2]) @ T_prev
            return T_prev @ d
        return T_prev.copy()

    def _two_view_ground_baseline(self, fo: FrontendOutput, t_unit: np.ndarray) -> float | None:
        """Length of the first baseline that puts the floor at the camera's known height."""
        assert fo.R_cam_kf_cam is not None
        T_cur_kf = make_T(fo.R_cam_kf_cam, t_unit)
        # Both keyframes in a unit-baseline world anchored at keyframe 0's base.
        T_b0_c1 = self.T_base_cam @ inv_T(T_cur_kf)
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

    def _motion_factors(self, graph, values, stamps, k: int, odom: OdometryStep | None, T_guess) -> None:
        """First-pose prior, wheel factors (through the calibration state) or a monocular motion prior."""
        if k == 0:
            graph.add(fac.first_pose_prior(X(0), np.eye(4)))
            return
        usable = odom is not None and self._odometry_usable(odom)
        calib_key = self._calibration_state(graph, values, stamps, k) if self.calibrate else None
        if calib_key is not None and odom is not None:
            self.calib_distance_m += odom.distance_m
        if usable:
            assert odom is not None
            for f in fac.odometry_factors(self.cfg, k, odom.T_prev_cur, odom.distance_m, calib_key):
                graph.add(f)
            return
        delta = inv_T(self.kf_pose[k - 1]) @ T_guess
        graph.add(fac.monocular_motion_factor(k, delta, first_baseline=(k == 1 and not self.use_odometry)))

    def _calibration_block_starts(self, k: int) -> bool:
        """A new calibration state starts with each block of keyframes that leaves the window together."""
        return (k + self.cfg.window_keyframes - 1) % self.cfg.marginalize_every == 0

    def _calibration_state(self, graph, values, stamps, k: int) -> int:
        """Key of the calibration state keyframe k's wheel step goes through.

        One state per block of ``marginalize_every`` keyframes (the blocks that leave the window
        together), not per keyframe: the calibration drifts over tens of metres, a block spans a
        metre or two, and every extra state joins the dense block of poses iSAM2 re-eliminates at
        each update (one per keyframe made the back end ~50% slower). A new state ``C(k)`` joins with
        a prior (the first one) or a random walk from the previous one, so the chain never breaks; a
        state in use has its timestamp refreshed, so it leaves with the last pose whose step it holds."""
        release = self._release_scale
        self._release_scale = False
        if (k != self.calib_start and self.calib_key >= 0 and not self._calibration_block_starts(k)
                and not release):
            stamps[C(self.calib_key)] = float(k)
            return C(self.calib_key)
        values.insert(C(k), np.array([self.calib.scale, self.calib.yaw_bias_per_m]))
        stamps[C(k)] = float(k)
        if k == self.calib_start or self.calib_key < 0:
            wc = self.cfg.wheel_calibration
            graph.add(fac.calibration_prior(k, self.calib.scale, self.calib.yaw_bias_per_m,
                                            wc.scale_prior_sigma, wc.yaw_bias_prior_sigma))
        else:
            graph.add(fac.calibration_random_walk(self.cfg, self.calib_key, k, self.calib_distance_m,
                                                  release_scale=release))
        self.calib_key, self.calib_distance_m = k, 0.0
        return C(k)

    def _update(self, fo: FrontendOutput, odom, T_guess, use_vision: bool, allow_new: bool) -> tuple[int, int, int]:
        """One keyframe: its pose and motion factors, its observations and new landmarks (with their ground
        factors), one smoother update, then the landmark bookkeeping. Returns (new landmarks, projection
        factors, ground factors)."""
        k = self.k
        if self.calibration_wanted and not self.calibrate and self.n_ground_keyframes > 0:
            self.calibrate, self.calib_start = True, k
            log.info("keyframe %d: the floor is in view; wheel scale and yaw bias are now estimated online", k)
        self._judge_mount()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {}
        self.level_frame = self.floor_normal_learnt = False
        self._pose_factors(graph, values, stamps, odom, T_guess)
        # Outlier landmarks flagged after the previous update: remove their factors; the key stays
        # alive with its birth prior until it is marginalised.
        remove = self.lm.take_removals()
        # Per factor: (track id, keyframe, is a native ground factor), or None.
        owners: list[tuple[int, int, bool] | None] = [None] * graph.size()
        w0 = self.window_start(k)
        if self._retie_floor:
            remove = remove + self._retie_window_floor(graph, owners, w0)
        new_lms: list[int] = []
        n_vis = n_ground = 0
        if use_vision:
            n_vis, candidates = self._observation_factors(graph, stamps, owners, fo, allow_new)
            new_lms, n_born_vis, n_ground = self._new_landmark_factors(graph, values, stamps, owners, candidates,
                                                                       w0, T_guess)
            n_vis += n_born_vis
        idx = self._solve(graph, values, stamps, remove, new_lms)
        self.lm.record_factors(owners, idx)
        self.n_ground_factors += n_ground
        self.n_ground_keyframes += int(n_ground > 0)
        self._refresh_states()
        self.lm.prune(w0)
        self._untie_off_floor(w0)
        ids, p_world, uv = self.lm.seen_now(fo.track_ids, fo.pixels_undistorted, k)
        errs = reprojection_errors(self.camera, self.kf_pose[k], self.T_base_cam, p_world, uv)
        self.lm.check_outliers(ids, errs, self.window_start(k + 1))
        return len(new_lms), n_vis, n_ground

    def _pose_factors(self, graph, values, stamps: dict[int, float], odom: OdometryStep | None, T_guess) -> None:
        """The new keyframe's pose, its motion factors and the planar attitude (and height) priors."""
        k, cfg = self.k, self.cfg
        values.insert(X(k), gtsam.Pose3(T_guess))
        stamps[X(k)] = float(k)
        self._motion_factors(graph, values, stamps, k, odom, T_guess)
        if cfg.planar_prior.enabled and k > 0:
            graph.add(fac.planar_attitude_factor(X(k), cfg))
            if cfg.planar_prior.height_prior:
                graph.add(fac.height_prior_factor(X(k), T_guess, cfg.planar_prior.height_sigma_m))

    def _observation_factors(self, graph, stamps: dict[int, float], owners: list, fo: FrontendOutput,
                             allow_new: bool) -> tuple[int, list[int]]:
        """Projection factors of the landmarks the new keyframe sees. Returns their number and the tracks
        that may become landmarks now."""
        k = self.k
        seen, candidates = self.lm.observe(fo.track_ids, fo.pixels_undistorted, k, allow_new, fo.pixel_sigma_scale)
        for tid, uv, sc in seen:
            key = self.lm.landmarks[tid].key
            graph.add(fac.projection_factor(uv, X(k), key, self._pixel_noise(sc), self.K, self.body_P_sensor))
            owners.append((tid, k, False))
            stamps[key] = float(k)
        return len(seen), candidates

    def _new_landmark_factors(self, graph, values, stamps: dict[int, float], owners: list, candidates: list[int],
                              w0: int, T_guess: np.ndarray) -> tuple[list[int], int, int]:
        """New landmarks (within the budgets): each with its birth prior, its projection factors in the
        window and, on the floor, its ground factor. Returns (their track ids, projection factors, ground
        factors)."""
        k = self.k
        poses = {kk: self.kf_pose[kk] for kk in range(w0, k)}
        poses[k] = T_guess
        cams = LandmarkManager.camera_poses(poses, self.T_base_cam)
        budgets = self._budgets()  # no landmark is born before both uses below
        born = self._triangulate_candidates(candidates, cams, T_guess, budgets)
        on_floor, floor_fit = self._floor_of(born, T_guess)
        born, on_floor = self._within_budget(born, on_floor, budgets)
        up_world = self._level_up(T_guess, floor_fit if on_floor.any() else None)
        n_base = self.floor_normal_base()  # the same for all of this keyframe's floor points
        cam_center = (T_guess @ self.T_base_cam)[:3, 3]
        new_lms: list[int] = []
        n_vis = n_ground = 0
        for (tid, p), floor in zip(born, on_floor):
            key = fac.G(tid) if floor else L(tid)
            values.insert(key, gtsam.Point3(p))
            stamps[key] = float(k)
            graph.add(fac.landmark_birth_prior(key, p, float(np.linalg.norm(p - cam_center))))
            owners.append(None)
            for kk, uv_k, sc in self.lm.promote(tid, k, bool(floor)):
                if kk >= w0:
                    graph.add(fac.projection_factor(uv_k, X(kk), key, self._pixel_noise(sc), self.K,
                                                    self.body_P_sensor))
                    owners.append((tid, kk, False))
                    n_vis += 1
            if floor and not self._waiting_for_floor():
                graph.add(self._birth_ground_factor(key, p, T_guess, up_world, n_base))
                owners.append((tid, k, up_world is None))
                n_ground += 1
            new_lms.append(tid)
        return new_lms, n_vis, n_ground

    def _birth_ground_factor(self, key: int, p_world: np.ndarray, T_guess: np.ndarray,
                             up_world: np.ndarray | None, n_base: np.ndarray | None):
        """A new floor landmark's ground factor at its birth keyframe: along the base's z axis (or the
        learnt floor normal ``n_base``) natively, or along the level frame's up when the base rocks."""
        k, cfg = self.k, self.cfg
        self.floor_normal_learnt = n_base is not None
        if up_world is not None:
            self.n_level_ground_factors += 1
            self.level_frame = True
            return fac.level_ground_factor(X(k), key, up_world, self.floor_z, self.ground_sigma_m, cfg)
        p_base = (p_world - T_guess[:3, 3]) @ T_guess[:3, :3]
        return fac.ground_factor(X(k), key, p_base, self.floor_offset(n_base), self.ground_sigma_m, cfg, n_base)

    def _solve(self, graph, values, stamps: dict[int, float], remove: list[int], new_lms: list[int]) -> list[int]:
        """One smoother update (plus ``extra_iterations``) and the new estimate; the new factors' indices."""
        k, cfg = self.k, self.cfg
        ts_map = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, t in stamps.items():
            ts_map.insert((key, t))
        try:
            idx = self._submit(graph, values, ts_map, remove)
            for _ in range(cfg.extra_iterations if k > 2 else 2):
                self.smoother.update()  # more Gauss-Newton steps (iSAM2 takes one per update)
            self.estimate = self.smoother.calculateEstimate()
        except RuntimeError:
            # Undo the bookkeeping of this update before the caller resets the window.
            self.lm.forget(new_lms)
            raise
        return idx

    # ------------------------------------------------------------------ late metric start (monocular)
    def _floor_scale_now(self) -> float | None:
        """Up to scale: the factor that would put the floor plane under the window's landmarks at the camera's
        known height (None: no floor plane in view), as at the monocular start, with a refining second fit."""
        _, pts = self.lm.positions()
        T_wb = self.kf_pose[self.k]
        rel = (pts - (T_wb @ self.T_base_cam)[:3, 3]) @ T_wb[:3, :3]
        height = camera_height_up_to_scale(rel, self.cfg.ground, self._rng, refine=True)
        return None if height is None else self.camera_height_m / height

    def _late_metric_start(self, fo: FrontendOutput) -> dict[int, np.ndarray] | None:
        """A monocular run with no floor in its first two keyframes is up to scale until the floor comes into
        view. When two consecutive keyframes' floor planes agree on the scale, every keyframe pose is
        rescaled about the first camera centre, the window restarts from this keyframe (metric now, so the
        ground factors hold the scale from here on), and the run is metric. Returns the rescaled poses of the
        keyframes before the window (the window's go out as usual), or None when the run stays up to scale."""
        scale = self._floor_scale_now()
        prev, self._late_scale = self._late_scale, scale
        if scale is None or prev is None or not _floors_agree(prev, scale):
            return None
        s = float(np.sqrt(scale * prev))
        c0 = (self.kf_pose[0] @ self.T_base_cam)[:3, 3]
        base_from_cam = inv_T(self.T_base_cam)
        for kk, T_wb in self.kf_pose.items():
            T_wc = T_wb @ self.T_base_cam
            T_wc[:3, 3] = c0 + s * (T_wc[:3, 3] - c0)
            self.kf_pose[kk] = T_wc @ base_from_cam
        self.metric, self.metric_from_keyframe = True, self.k
        self._restart_window(fo, None, self.kf_pose[self.k], with_previous=False)
        log.info("keyframe %d (frame %d): the floor is in view; the run is metric from here (scale x %.3f), the "
                 "trajectory so far rescaled", self.k, fo.frame_index, s)
        return {self.kf_frame[kk]: self.kf_pose[kk] for kk in range(self.window_start()) if kk in self.kf_pose}

    def _pixel_noise(self, stretch: float):
        """Projection noise of one observation: the lens's stretch of the undistortion at that pixel scales
        the sensor's pixel sigma (exactly 1 for a pinhole, up to 1/cos^2 of the ray angle for a fisheye)."""
        if not self.cfg.propagate_lens_noise or abs(stretch - 1.0) < 0.05:
            return self.pixel_noise
        return fac.pixel_noise(self.cfg, stretch)

    def _ground_active(self) -> bool:
        return self.use_ground and self.metric

    def _waiting_for_floor(self) -> bool:
        """A monocular run that saw no floor at its start: up to scale until ``_late_metric_start``."""
        return self.use_ground and not self.metric

    def _triangulate_candidates(self, candidates: list[int], cams, T_guess: np.ndarray,
                                budgets: tuple[int, int]) -> list[tuple[int, np.ndarray]]:
        """Triangulate tracks, longest first, while the landmark budgets (others, floor) have room.

        Floor landmarks fix the metric scale, so tracks below the horizon have a budget of their own
        (``ground.max_landmarks``) besides the window's ``max_landmarks``."""
        reg_left, floor_left = budgets
        below = self._below_horizon(candidates, T_guess) if floor_left > 0 else np.zeros(len(candidates), bool)
        born: list[tuple[int, np.ndarray]] = []
        # All at once (vectorised); then taken in order while the budgets have room.
        wanted = [tid for tid, is_below in zip(candidates, below) if (floor_left if is_below else reg_left) > 0]
        points = dict(zip(wanted, self.lm.triangulate(wanted, cams)))
        for tid, is_below in zip(candidates, below):
            if reg_left <= 0 and floor_left <= 0:
                break
            if (floor_left if is_below else reg_left) <= 0:
                continue
            p = points[tid]
            if p is None:
                continue
            born.append((tid, p))
            if is_below:
                floor_left -= 1
            else:
                reg_left -= 1
        return born

    def _budgets(self) -> tuple[int, int]:
        """Room for new landmarks now: (others, floor). Landmarks count against the budgets while a
        keyframe among the last ``window_keyframes + 1`` saw them: with ``marginalize_every`` 1 that is
        every landmark the smoother holds during an update; with blocks, those waiting for their block
        to leave do not take new ones' places. A monocular run still waiting for the floor (``_waiting_for_floor``)
        keeps the floor's budget for tracks below the horizon, so the floor, once in view, is in the window."""
        return self.lm.budgets(self.cfg.ground.max_landmarks if self.use_ground else 0,
                               self.k - self.cfg.window_keyframes)

    def _below_horizon(self, tids: list[int], T_guess: np.ndarray) -> np.ndarray:
        """Whether each track's newest ray points below the horizon (a cheap floor pre-check)."""
        if not tids:
            return np.zeros(0, bool)
        uv = np.asarray([self.lm.obs[t][-1][1] for t in tids])
        K = self.camera
        rays = np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(uv))], axis=1)
        d = rays @ self.T_base_cam[:3, :3].T
        dep = np.degrees(np.arctan2(-d[:, 2], np.hypot(d[:, 0], d[:, 1])))
        return dep >= self.cfg.ground.min_depression_deg

    def _within_budget(self, born: list[tuple[int, np.ndarray]], on_floor: np.ndarray, budgets: tuple[int, int]
                       ) -> tuple[list[tuple[int, np.ndarray]], np.ndarray]:
        """Keep floor landmarks within the floor budget and the others within the window's budget."""
        reg_left, floor_left = budgets
        keep = []
        for i, floor in enumerate(on_floor):
            if floor and floor_left > 0:
                floor_left -= 1
                keep.append(i)
            elif reg_left > 0:
                reg_left -= 1
                on_floor[i] = False
                keep.append(i)
        return [born[i] for i in keep], on_floor[keep]

    def _floor_of(self, born: list[tuple[int, np.ndarray]], T_guess: np.ndarray
                  ) -> tuple[np.ndarray, PlaneFit | None]:
        """Which new landmarks lie on the floor (plane fitted over the window's landmarks and them), and
        the plane (base frame of ``T_guess``).

        On a level base the ground factor takes the base's own xy plane as the floor (a rocking one:
        ``_level_up``). Measured against it: a normal
        refitted per keyframe was noisier than the base attitude the smoother estimates from all the
        evidence, and a mean of the last 30 keyframes' normals (for a camera pitched on its mount) took
        up a ramp's tilt ahead (rendered ramp 0.012 -> 0.051 m) without helping on KITTI."""
        if self._waiting_for_floor() and born:
            # No metric height to fit a floor plane at yet: below the horizon is all that is known.
            return self._below_horizon([tid for tid, _ in born], T_guess), None
        if not self._ground_active() or not born:
            return np.zeros(len(born), bool), None
        new_pts = np.asarray([p for _, p in born])
        old_pts = self.lm.positions()[1]
        pts = np.concatenate([new_pts, old_pts])
        mask, fit = floor_mask(pts, T_guess, self.T_base_cam, self.camera_height_m, self.cfg.ground, self._rng)
        if fit is None and not self.use_odometry:
            mask, fit = self._floor_after_scale_drift(pts, T_guess)
        else:
            self._drift_height = None
        fa = self.floor_attitude
        if fit is not None:
            fa.add(fit.normal)
            if self.cfg.ground.mount_calibration is MountCalibration.ON and not fa.ready:
                # Still learning the floor's attitude on the mount: floor points tied to a floor the mount
                # may be tilted against would set a wrong scale (and the wheel calibration with it), which
                # the calibration's slow random walk then carries for the rest of the run.
                return np.zeros(len(born), bool), fit
        return mask[: len(born)], fit

    def _floor_after_scale_drift(self, pts: np.ndarray, T_guess: np.ndarray) -> tuple[np.ndarray, PlaneFit | None]:
        """The floor of a monocular run whose scale drifted (no wheels: the floor is its only scale source).

        While no floor is in view the scale drifts like any monocular run's (KITTI 01 on the highway: 35%
        in 7 keyframes without floor tracks); when the floor is back, it lies at a height the metric fit
        rejects (``height_tolerance``), and the run would stay drifted. A plane found at the same height at
        two consecutive keyframes (``_floors_agree``, as at the late metric start: one plane could be a
        table top) is taken as the floor again: its ground factors pull the scale back."""
        mask, fit = floor_mask(pts, T_guess, self.T_base_cam, self.camera_height_m, self.cfg.ground, self._rng,
                               metric_scale_known=False)
        prev, self._drift_height = self._drift_height, (None if fit is None else fit.camera_height_m)
        if fit is None or prev is None or not _floors_agree(prev, fit.camera_height_m):
            return np.zeros(len(pts), bool), None
        self.n_scale_reanchors += 1
        log.info("keyframe %d: the floor is back, %.2f x the camera height below the camera (the scale drifted "
                 "while it was out of view); tied to it again", self.k, fit.camera_height_m / self.camera_height_m)
        return mask, fit

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

    def _retie_window_floor(self, graph, owners: list, w0: int) -> list[int]:
        """Tie the window's floor landmarks to the floor along the learnt normal instead of the base z axis
        (at the switch of ``_judge_mount``): their ground factors are replaced, so the keyframes still in
        the window lose the scale the wrong floor gave them. Returns the factor indices to remove."""
        self._retie_floor = False
        n_base = self.floor_normal_base()
        offset = self.floor_offset(n_base)
        removed = []
        for tid, kk, fi, p_world in self.lm.tied_to_floor(w0):
            T = self.kf_pose[kk]
            p_base = (p_world - T[:3, 3]) @ T[:3, :3]
            key = self.lm.landmarks[tid].key
            graph.add(fac.ground_factor(X(kk), key, p_base, offset, self.ground_sigma_m, self.cfg, n_base))
            owners.append((tid, kk, True))
            self.lm.drop_factor(tid, kk, fi)
            removed.append(fi)
        log.info("keyframe %d: %d floor landmarks of the window re-tied along the learnt normal", self.k, len(removed))
        return removed

    def _untie_off_floor(self, w0: int) -> None:
        """Remove (at the next update) the ground factors of the window's floor landmarks whose height above the
        floor of the keyframe that tied them, in the new estimate, strays from the others' (``ground.off_floor``).

        Only native ground factors (``lm.ground_factor``); the level frame's, on a rocking base, are left alone.
        Measured (README, Performance): a loop lined with 3 cm kerbs, wheels +2%: ATE SE(3) 0.041 -> 0.017 m
        (without wheels 0.097 -> 0.023 m); 19 plain loops and figure eights 0.94x-1.31x, geometric mean 1.04."""
        k_sigma = self.cfg.ground.untie_sigmas
        if k_sigma is None:
            return
        n_base = self.floor_normal_base()
        up = np.array([0.0, 0.0, 1.0]) if n_base is None else n_base
        offset = self.floor_offset(n_base)
        tied = self.lm.tied_to_floor(w0)
        if not tied:
            return
        # Height along ``up`` in the tying keyframe's base frame: up . R^T (p - t), for all points at once.
        T = np.stack([self.kf_pose[kk] for _, kk, _, _ in tied])
        p = np.stack([p_world for *_, p_world in tied])
        heights = np.einsum("nij,ni,j->n", T[:, :3, :3], p - T[:, :3, 3], up) - offset
        off = off_floor(heights, k_sigma, UNTIE_MIN_SIGMA_HEIGHTS * self.camera_height_m)
        for (tid, kk, fi, _), is_off in zip(tied, off):
            if is_off:
                self.lm.drop_factor(tid, kk, fi)
                self.lm.pending_removal.append(fi)
                self.n_floor_untied += 1

    def _judge_mount(self) -> None:
        """``ground.mount_calibration`` auto: switch to the learnt floor normal once its tilt is significant.

        Until then the floor points were tied to the base's xy plane, which a tilted mount makes the wrong
        floor. So at the switch the window's floor landmarks are re-tied along the learnt normal
        (``_retie_window_floor``), and since the scale they gave also went into the wheel calibration,
        which its slow random walk would carry for tens of metres, the calibration's scale is released
        once (its next state joins with a random walk as wide as its prior). Measured on loops whose
        camera.yaml is 0.5 / 1 / -1 deg off: 0.13-0.26 m -> 0.010-0.021 m (README, mount study)."""
        if (self.cfg.ground.mount_calibration is not MountCalibration.AUTO or self.mount_normal_used
                or not self.floor_attitude.significant()):
            return
        self.mount_normal_used = self._release_scale = self._retie_floor = True
        tx, ty = self.floor_attitude.tilt_deg()
        released = ", and the wheel calibration's scale is released" if self.calibrate else ""
        log.warning("keyframe %d: the floor is tilted %.2f deg in the base frame (T_base_cam's pitch or roll looks "
                    "off by that): floor heights are measured along the learnt normal from here on%s", self.k,
                    float(np.hypot(tx, ty)), released)

    def _level_up(self, T_guess: np.ndarray, fit: PlaneFit | None) -> np.ndarray | None:
        """The floor's normal (world) to measure this keyframe's floor points along when the base rocks,
        else None (the native factor in the keyframe's own base frame).

        Measured on 20 rendered sequences rocking by 0.7-2 deg (README, Performance): ATE 0.42x-1.71x of
        the native factor's, geometric mean 0.87x; wheel scale 0.02-0.59% off (mean 0.22%) instead of
        0.02-0.82% (mean 0.32%). Level runs and the ramp never reach ``ground.rocking_jitter_deg``, so
        they keep the native factor, which also holds each keyframe's attitude to the floor (the level
        frame everywhere cost them 1.07x on average over ten seeds, the ramp 1.25x)."""
        g = self.cfg.ground
        w0 = self.window_start()
        Rs = [self.kf_pose[kk][:3, :3] for kk in range(w0, self.k) if kk in self.kf_pose]
        z_axes = np.array([R[:, 2] for R in Rs]).reshape(-1, 3)
        self.base_rocking_deg = attitude_jitter_deg(z_axes) if len(z_axes) >= MIN_ROCKING_KEYFRAMES else float("nan")
        if g.rocking_jitter_deg is None or fit is None or not self.base_rocking_deg > g.rocking_jitter_deg:
            return None
        if self.n_level_ground_factors == 0:
            log.info("keyframe %d: the base rocks (median tilt change %.2f deg between keyframes): floor points "
                     "are measured along the floor's normal while it does", self.k, self.base_rocking_deg)
        n_base = self.floor_normal_base()
        floor_normals = z_axes if n_base is None else np.array([R @ n_base for R in Rs])
        return level_up(floor_normals, T_guess[:3, :3] @ fit.normal, g.level_select_deg)

    def _submit(self, graph, values, ts_map, remove) -> list[int]:
        """One smoother update; returns the smoother's indices of the new factors."""
        # Keys stamped before the window start are marginalised in this update (none between blocks).
        self.smoother.setSmootherLag(float(self.k - self.window_start()))
        self.smoother.update(graph, values, ts_map, remove)
        return list(self.smoother.getISAM2Result().getNewFactorsIndices())

    def _refresh_states(self) -> None:
        est = self.estimate
        assert est is not None
        for kk in range(self.window_start(), self.k + 1):
            if est.exists(X(kk)):
                self.kf_pose[kk] = est.atPose3(X(kk)).matrix()
        if self.calibrate and est.exists(C(self.calib_key)):
            c = est.atPoint2(C(self.calib_key))
            self.calib.scale, self.calib.yaw_bias_per_m = float(c[0]), float(c[1])

    def calibration_with_sigma(self) -> WheelCalibration:
        """The newest calibration estimate with its marginal sigmas (computed on request: costs a solve)."""
        cal = WheelCalibration(self.calib.scale, self.calib.yaw_bias_per_m)
        if self.calibrate and self.estimate is not None and self.estimate.exists(C(self.calib_key)):
            try:
                cov = self.smoother.marginalCovariance(C(self.calib_key))
                cal.scale_sigma, cal.yaw_bias_sigma = float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))
            except RuntimeError as err:  # pragma: no cover - diagnostics only
                log.debug("no marginal covariance of the calibration: %s", err)
        return cal

    def _reset_with(self, fo: FrontendOutput, odom, T_guess: np.ndarray) -> None:
        """Start a fresh window from the last good pose and calibration; this keyframe rests on odometry.

        If even that fails, the window restarts from this keyframe's guess alone; if that fails too,
        the run stops with a clear error (the pipeline still writes what it has)."""
        self.n_resets += 1
        try:
            self._restart_window(fo, odom, T_guess, with_previous=self.k > 0)
        except RuntimeError as err:
            log.warning("keyframe %d: reset from the last good pose failed (%s); restarting from this keyframe",
                        self.k, " ".join(str(err).split())[:200])
            try:
                self._restart_window(fo, None, T_guess, with_previous=False)
            except RuntimeError as err2:
                raise WindowVOError(f"the smoother could not restart at keyframe {self.k} (frame "
                                    f"{fo.frame_index}): {' '.join(str(err2).split())[:200]}") from None

    def _restart_window(self, fo: FrontendOutput, odom, T_guess: np.ndarray, with_previous: bool) -> None:
        k = self.k
        self._new_smoother()
        self.lm.restart(k, fo.track_ids, fo.pixels_undistorted, fo.pixel_sigma_scale)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {}
        if self.calibrate and self.calib_start >= self.k:  # the calibration started in the failed update
            self.calibrate, self.calib_start, self.calib_key = False, -1, -1
        if with_previous:
            T_prev = self.kf_pose.get(k - 1, np.eye(4))
            graph.add(fac.reset_prior(X(k - 1), T_prev, self.cfg))
            values.insert(X(k - 1), gtsam.Pose3(T_prev))
            stamps[X(k - 1)] = float(k - 1)
            if self.calibrate:
                wc = self.cfg.wheel_calibration
                f = RESET_CALIBRATION_SIGMA_FACTOR
                values.insert(C(k - 1), np.array([self.calib.scale, self.calib.yaw_bias_per_m]))
                stamps[C(k - 1)] = float(k - 1)
                graph.add(fac.calibration_prior(k - 1, self.calib.scale, self.calib.yaw_bias_per_m,
                                                f * wc.scale_prior_sigma, f * wc.yaw_bias_prior_sigma))
                self.calib_key, self.calib_distance_m = k - 1, 0.0
            self._motion_factors(graph, values, stamps, k, odom, T_guess)
        else:
            graph.add(fac.first_pose_prior(X(k), T_guess))
            if self.calibrate:  # the chain restarts here from the last estimate with the full prior
                self.calib_start = k
                self._calibration_state(graph, values, stamps, k)
        values.insert(X(k), gtsam.Pose3(T_guess))
        stamps[X(k)] = float(k)
        ts_map = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, t in stamps.items():
            ts_map.insert((key, t))
        self.smoother.update(graph, values, ts_map)
        self.estimate = self.smoother.calculateEstimate()
        self.kf_pose[k] = self.estimate.atPose3(X(k)).matrix()
        if with_previous:
            self.kf_pose[k - 1] = self.estimate.atPose3(X(k - 1)).matrix()
        self._refresh_states()

    def _output(self, fo: FrontendOutput, n_new: int, n_vis: int, n_ground: int,
                status: BackendStatus) -> BackendOutput:
        assert self.estimate is not None
        ids, pts = self.lm.positions()
        _, p_seen, uv = self.lm.seen_now(fo.track_ids, fo.pixels_undistorted, self.k)
        rms = reprojection_rms(reprojection_errors(self.camera, self.kf_pose[self.k], self.T_base_cam, p_seen, uv))
        w0 = self.window_start()
        tilt = self.floor_attitude.tilt_deg() if self.floor_attitude.ready else (float("nan"), float("nan"))
        return BackendOutput(
            frame_index=fo.frame_index,
            timestamp=fo.timestamp,
            T_world_base=self.kf_pose[self.k].copy(),
            keyframe_poses={self.kf_frame[kk]: self.kf_pose[kk] for kk in range(w0, self.k + 1)},
            p_world_landmarks=pts,
            landmark_ids=ids,
            n_landmarks=len(ids),
            n_new_landmarks=n_new,
            n_vision_factors=n_vis,
            reprojection_rms_px=rms,
            status=status,
            n_ground_factors=n_ground,
            base_rocking_deg=self.base_rocking_deg,
            level_frame=self.level_frame,
            floor_tilt_x_deg=tilt[0],
            floor_tilt_y_deg=tilt[1],
            floor_tilt_se_deg=self.floor_attitude.standard_error_deg() if self.floor_attitude.ready else float("nan"),
            floor_normal_learnt=self.floor_normal_learnt,
            wheel_scale=self.calib.scale if self.calibrate else float("nan"),
            wheel_yaw_bias_per_m=self.calib.yaw_bias_per_m if self.calibrate else float("nan"),
        )
