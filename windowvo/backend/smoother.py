"""The back end's window: keys, timestamps, iSAM2 (GTSAM's fixed-lag smoother), reset.

``SlidingWindowBackend.add_keyframe`` takes one keyframe's tracks and wheel step and submits one
update, asking the others for its parts: the factor builders (``factors.py``) for factors, the
landmark manager (``landmarks.py``) for landmarks, the wheel calibration states
(``wheel_calibration.py``, ``WheelCalibrationStates``) for the calibration state a wheel step goes
through, the vision part (``landmark_factors.py``, ``LandmarkFactors``) for projection factors and new
landmarks, and the floor model (``floor.py``, ``FloorModel``: all floor state) for floor landmarks, the
floor they are tied to and their ground factors. ``_update`` builds the update in steps: the pose and
its motion factors (``_pose_factors``), the observations of known landmarks
(``LandmarkFactors.observation_factors``), new landmarks with their ground factors
(``LandmarkFactors.new_landmark_factors``), the smoother update (``_solve``, through ``submit``). This
module owns the window: keys and timestamps, the lag, the iSAM2 update, the estimate, and the reset
(``_reset_with``, ``restart_window``); it also rescales the trajectory at a monocular run's late
metric start (``FloorModel.late_metric_start`` says when and by how much).

States: ``X(k)`` is ``T_world_base`` of keyframe k, ``L(id)`` the world position of the landmark
of track ``id`` (``G(id)`` for a floor landmark), ``C(k)`` the wheel calibration (distance scale, yaw bias per metre, yaw scale) from keyframe k on,
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
from ..config import BackendConfig
from ..errors import WindowVOError
from ..geometry import extrapolate_T, inv_T, two_view_pose, with_tilt_of
from ..runtime.stage_timer import Laps, Stage, mark_keyframe
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
from .floor import FloorModel, observe_motion
from .landmark_factors import LandmarkFactors
from .landmarks import LandmarkManager, reprojection_errors, reprojection_rms
from .report import ScaleReport, scale_report, scale_sources
from .road_region import RoadRegion
from .wheel_calibration import WheelCalibrationStates
from .wheel_climb import WheelClimb
from .wheel_slip import WheelSlipSwitch

log = logging.getLogger(__name__)

__all__ = ["C", "L", "OdometryStep", "SlidingWindowBackend", "X"]


class SlidingWindowBackend:
    """Fixed-lag smoother fed one keyframe at a time."""

    def __init__(self, camera: CameraModel, cfg: BackendConfig, use_odometry: bool):
        self.camera = camera
        self.cfg = cfg
        self.use_odometry = use_odometry
        self.K = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
        self.T_base_cam = camera.T_base_cam
        self.body_P_sensor = gtsam.Pose3(camera.T_base_cam)
        self.lag = float(cfg.window_keyframes - 1)
        self.lm = LandmarkManager(camera, cfg)
        self.k = -1
        self.kf_frame: dict[int, int] = {}
        self.kf_time: dict[int, float] = {}
        self.kf_pose: dict[int, np.ndarray] = {}  # latest estimate; final once marginalised
        # The wheel calibration states C(k) (live once the floor is in view) and the ground cue.
        self.wheel = WheelCalibrationStates(cfg, use_odometry)
        self.slip = WheelSlipSwitch(cfg)  # a wheel step the window's solution rejects is switched off
        self.climb = WheelClimb(cfg)  # odometry.climb_sigma_per_m: consecutive wheel steps' change of climb rate
        self.floor = FloorModel(camera, cfg, use_odometry, self.lm, self.kf_pose)
        self.vision = LandmarkFactors(camera, cfg, self.lm, self.floor, self.kf_pose, self.K, self.body_P_sensor)
        # ground.road_region (does nothing when off)
        self.road = RoadRegion(camera, cfg, self.floor, self.kf_pose, with_wheels=use_odometry)
        self._estimate: gtsam.Values | None = None
        self.n_resets = 0
        self._new_smoother()

    # ------------------------------------------------------------------ what the floor model and calibration own
    @property
    def use_ground(self) -> bool:
        """The ground cue is on (``ground.enabled`` and a camera high enough above the floor)."""
        return self.floor.use_ground

    @property
    def camera_height_m(self) -> float:
        return self.floor.camera_height_m

    @property
    def metric(self) -> bool:
        """The run's scale is metric (wheels, or the floor at the camera's known height)."""
        return self.floor.metric

    @metric.setter
    def metric(self, value: bool) -> None:
        self.floor.metric = value

    @property
    def metric_from_keyframe(self) -> int | None:
        """A late metric start: the keyframe it happened at."""
        return self.floor.metric_from_keyframe

    @property
    def n_scale_reanchors(self) -> int:
        return self.floor.n_scale_reanchors

    @property
    def n_floor_untied(self) -> int:
        return self.floor.n_floor_untied

    @property
    def n_ground_factors(self) -> int:
        return self.floor.n_ground_factors

    @property
    def calibrate(self) -> bool:
        """The wheel calibration states C(k) are live."""
        return self.wheel.calibrate

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
        return scale_sources(self)  # report.py says what fixes the scale

    def calibration_with_sigma(self) -> WheelCalibration:
        """The newest calibration estimate with its marginal sigmas (computed on request: costs a solve)."""
        return self.wheel.with_sigma(self.smoother, self.estimate)

    # ------------------------------------------------------------------ main entry
    def add_keyframe(self, fo: FrontendOutput, odom: OdometryStep | None) -> BackendOutput:
        t0 = time.perf_counter()
        lap = Laps()
        mark_keyframe()
        self.k += 1
        k = self.k
        self.kf_frame[k] = fo.frame_index
        self.kf_time[k] = fo.timestamp
        status = BackendStatus.OK
        # New landmarks need a vision-worthy keyframe; each one is still checked for its own
        # triangulation angle, so low overall parallax (distant scenes, turning) does not block it.
        allow_new = fo.gate in (GateOutcome.PASS, GateOutcome.LOW_PARALLAX) or k == 1
        T_guess = self._initial_guess(fo, odom)
        lap(Stage.BACKEND_GUESS)
        n_new = n_vis = n_ground = 0
        earlier: dict[int, np.ndarray] | None = None
        try:
            n_new, n_vis, n_ground = self._update(fo, odom, T_guess, fo.vision_ok, allow_new)  # times its own steps
            lap.skip()
            if k == 0:
                status = BackendStatus.INIT
            elif not fo.vision_ok:
                status = BackendStatus.ODOMETRY_FALLBACK
            elif self.floor.waiting_for_floor() and k >= 2:
                earlier = late_metric_start(self, fo)
            lap(Stage.BACKEND_FLOOR)
        except RuntimeError as err:
            lap.skip()
            msg = " ".join(str(err).split())[:300]
            log.warning("keyframe %d (frame %d): smoother failed (%s); resetting the window from the last good pose",
                        k, fo.frame_index, msg)
            self.slip.forget()
            self._reset_with(fo, odom, T_guess)
            self.road.forget()
            status = BackendStatus.RECOVERED
            lap(Stage.BACKEND_ISAM2)  # a fresh smoother from the last good pose
        out = keyframe_output(self, fo, n_new, n_vis, n_ground, status)
        if earlier is not None:
            out.metric_start, out.earlier_keyframe_poses = True, earlier
        lap(Stage.BACKEND_ESTIMATE)
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
        T_pnp = self.lm.pnp_pose(fo.track_ids, fo.pixels_undistorted, self.cfg.pixel_sigma)
        if odom is not None and self._odometry_usable(odom):
            # The wheels give the planar step; they cannot see the base's roll and pitch (their step is level in the
            # previous keyframe's frame), which a rocking base changes between keyframes and vision sees. PnP's tilt
            # is taken when its pose is one the wheel factor would call an inlier (a wrong PnP is not followed).
            T_wheels = T_prev @ self.wheel.calib.correct(odom.T_prev_cur, odom.distance_m)
            step_yaw = float(np.arctan2(odom.T_prev_cur[1, 0], odom.T_prev_cur[0, 0]))
            if T_pnp is not None and fac.agrees_with_wheel_step(self.cfg, T_wheels, T_pnp, odom.distance_m, step_yaw):
                return with_tilt_of(T_wheels, T_pnp)
            if T_pnp is not None and self.slip.in_slip:  # the wheels slipped at the last keyframe: vision's pose
                return T_pnp
            return T_wheels
        if T_pnp is not None:
            return T_pnp
        if k == 1 and fo.R_cam_kf_cam is not None and fo.t_dir_kf is not None:
            # Two-view initialisation: X_cur = R X_kf + t, with a unit baseline, or the metric one the
            # floor gives (camera at its known height).
            t_unit = fo.t_dir_kf / max(np.linalg.norm(fo.t_dir_kf), 1e-9)
            return two_view_pose(T_prev, self.T_base_cam, fo.R_cam_kf_cam, fo.t_dir_kf,
                                 self.floor.first_baseline(fo, t_unit, self.road.first_baseline) or 1.0)
        if k >= 2:  # constant velocity
            T_cv = extrapolate_T(self.kf_pose[k - 2], T_prev)
            if fo.R_cam_kf_cam is not None and fo.t_dir_kf is not None and self.cfg.uses_two_view_guess(self.use_odometry):
                # No PnP (the window's landmarks are out of view): the images' own rotation and direction
                # since the last keyframe, at the constant-velocity step's length (monocular: nothing else
                # knows the length), instead of extrapolating the last step's turn.
                return two_view_pose(T_prev, self.T_base_cam, fo.R_cam_kf_cam, fo.t_dir_kf,
                                     float(np.linalg.norm(T_cv[:3, 3] - T_prev[:3, 3])))
            return T_cv
        return T_prev.copy()

    def _motion_factors(self, graph, values, stamps, k: int, odom: OdometryStep | None, T_guess,
                        restart: bool = False) -> None:
        """First-pose prior, wheel factors (through the calibration state) or a monocular motion prior; a monocular
        run's first step and its first after a reset (``restart``: a fresh window) fix the gauge of scale by length."""
        if k == 0:
            graph.add(fac.first_pose_prior(X(0), np.eye(4)))
            return
        usable = odom is not None and self._odometry_usable(odom)
        calib_key = self.wheel.step_key(graph, values, stamps, k, None if odom is None else odom.distance_m)
        if usable:
            assert odom is not None
            for f in fac.odometry_factors(self.cfg, k, odom.T_prev_cur, odom.distance_m, calib_key):
                graph.add(f)
            if not restart and calib_key is not None:
                # The planar part (the last factor) is judged on this update's solution, once the floor holds the
                # window's scale (a calibrated step): where the wheels alone set it, the solution's scale is theirs
                # and a step cannot be judged against it (wheel_slip.py).
                self.slip.expect(graph.size() - 1, k, odom, calib_key)
            self.climb.add(graph, k, odom.distance_m, restart, self.window_start(k))  # after the slip's index
            return
        delta = inv_T(self.kf_pose[k - 1]) @ T_guess
        graph.add(fac.monocular_motion_factor(k, delta, first_baseline=(k == 1 or restart) and not self.use_odometry))

    def _update(self, fo: FrontendOutput, odom, T_guess, use_vision: bool, allow_new: bool) -> tuple[int, int, int]:
        """One keyframe: its pose and motion factors, its observations and new landmarks (with their ground
        factors), one smoother update, then the landmark bookkeeping. Returns (new landmarks, projection
        factors, ground factors)."""
        k = self.k
        lap = Laps()
        self.wheel.start_with_floor(k, self.floor.n_ground_keyframes + self.road.n_factors)
        observe_motion(self.floor.floor_attitude, fo, self.T_base_cam)
        self.floor.judge_mount(k)
        lap(Stage.BACKEND_FLOOR)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {}
        self.floor.begin_update()
        self.slip.begin_update()
        self._pose_factors(graph, values, stamps, odom, T_guess)
        self.road.add_factor(graph, self.window_start(k))
        # Outlier landmarks flagged after the previous update: remove their factors; the key stays
        # alive with its birth prior until it is marginalised.
        remove = self.lm.take_removals()
        # Per factor: (track id, keyframe, is a native ground factor), or None.
        owners: list[tuple[int, int, bool] | None] = [None] * graph.size()
        w0 = self.window_start(k)
        lap(Stage.BACKEND_FACTORS)
        if self.floor.retie_pending:
            remove = remove + self.floor.retie_window_floor(k, w0, graph, owners)
        lap(Stage.BACKEND_FLOOR)
        new_lms: list[int] = []
        n_vis = n_ground = 0
        if use_vision:
            n_vis, candidates = self.vision.observation_factors(k, w0, graph, stamps, owners, fo, allow_new)
            new_lms, n_born_vis, n_ground = self.vision.new_landmark_factors(k, w0, graph, values, stamps, owners,
                                                                             candidates, T_guess)
            n_vis += n_born_vis
            remove = remove + self.lm.take_removals()  # the slots of the smart factors replaced just now
        lap(Stage.BACKEND_FACTORS)
        idx = self._solve(graph, values, stamps, remove, new_lms, n_vis)  # times the update and the estimate itself
        lap.skip()
        self.lm.record_factors(owners, idx)
        self.floor.count_ground_factors(n_ground)
        self._refresh_states()
        lap(Stage.BACKEND_ESTIMATE)
        n_tied = self.lm.n_tied_to_floor(self.window_start()) if self.road.cue is not None else 0
        road_height = self.road.after_update(k, fo.image, fo.image_mask, n_tied, self.window_start())
        if k > 0 and self.slip.switched_now:
            self.floor.last_agreement = None  # a slipping step says nothing about the tyre's scale
        elif k > 0:
            step = np.linalg.norm(self.kf_pose[k][:3, 3] - self.kf_pose[k - 1][:3, 3])
            self.floor.check_cues(k, odom.distance_m if self._odometry_usable(odom) else None, float(step), road_height)
        lap(Stage.BACKEND_FLOOR)
        self.lm.prune(w0)
        lap(Stage.BACKEND_ESTIMATE)
        self.floor.untie_off_floor(w0)
        lap(Stage.BACKEND_FLOOR)
        ids, p_world, uv = self.lm.seen_now(fo.track_ids, fo.pixels_undistorted, k)
        errs = reprojection_errors(self.camera, self.kf_pose[k], self.T_base_cam, p_world, uv)
        self.lm.check_outliers(ids, errs, self.window_start(k + 1))
        lap(Stage.BACKEND_ESTIMATE)
        return len(new_lms), n_vis, n_ground

    def _pose_factors(self, graph, values, stamps: dict[int, float], odom: OdometryStep | None, T_guess) -> None:
        """The new keyframe's pose, its motion factors and the planar attitude (and height) priors."""
        k, cfg = self.k, self.cfg
        values.insert(X(k), gtsam.Pose3(T_guess))
        stamps[X(k)] = float(k)
        self._motion_factors(graph, values, stamps, k, odom, T_guess)
        self.floor.depth.step(graph, values, stamps, k, T_guess)
        if cfg.planar_prior.enabled and k > 0:
            graph.add(fac.planar_attitude_factor(X(k), cfg))
            if cfg.planar_prior.height_prior:
                graph.add(fac.height_prior_factor(X(k), T_guess, cfg.planar_prior.height_sigma_m))

    def _solve(self, graph, values, stamps: dict[int, float], remove: list[int], new_lms: list[int],
               n_vis: int = 0) -> list[int]:
        """One smoother update (plus ``extra_iterations``) and the new estimate; the new factors' indices. The new
        wheel step is then judged on that estimate (``wheel_slip.py``; ``n_vis``: this keyframe's projection
        factors): a step taken for slip is replaced (its heading alone, or nothing) and the window solved again."""
        ts_map, lap = gtsam.FixedLagSmootherKeyTimestampMap(), Laps()
        for key, t in stamps.items():
            ts_map.insert((key, t))
        try:
            idx = self.submit(graph, values, ts_map, remove)
            self._iterate(lap)
            switch = self.slip.judge(self.kf_frame[self.k], self.smoother, self.estimate, idx, n_vis)
            if switch is not None:
                self.submit(switch[1], gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap(),
                            [switch[0], *self.climb.switched(idx)])
                self._iterate(lap)
        except RuntimeError:
            # Undo the bookkeeping of this update before the caller resets the window.
            self.lm.forget(new_lms)
            raise
        return idx

    def _iterate(self, lap: Laps) -> None:
        """More Gauss-Newton steps (iSAM2 takes one per update), then the estimate, checked; ``lap`` gives the
        update before them and the steps to the iSAM2 stage, the estimate to its own."""
        for _ in range(self.cfg.extra_iterations if self.k > 2 else 2):
            self.smoother.update()
        lap(Stage.BACKEND_ISAM2)
        self.estimate = self.smoother.calculateEstimate()
        bad = diverged_keyframe(self.estimate, range(self.window_start(), self.k + 1))
        if bad is not None:  # a solve that ran off (e.g. a monocular run's scale collapsing): as a failed one
            raise RuntimeError(f"the estimate diverged: keyframe {bad}'s pose is not a rigid motion")
        lap(Stage.BACKEND_ESTIMATE)

    def submit(self, graph, values, ts_map, remove) -> list[int]:
        """One smoother update of keyframe ``k``'s new factors, values and stamps, removing the factors at the
        indices ``remove``; returns the smoother's indices of the new factors. (The one place an update
        enters the smoother: a test may wrap it to inject a failing update.)"""
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
        self.wheel.read(est)
        self.floor.depth.read(est)

    # ------------------------------------------------------------------ reset
    def _reset_with(self, fo: FrontendOutput, odom, T_guess: np.ndarray) -> None:
        """Start a fresh window from the last good pose and calibration; this keyframe rests on odometry.

        If even that fails, the window restarts from this keyframe's guess alone; if that fails too,
        the run stops with a clear error (the pipeline still writes what it has)."""
        self.n_resets += 1
        try:
            self.restart_window(fo, odom, T_guess, with_previous=self.k > 0)
        except RuntimeError as err:
            log.warning("keyframe %d: reset from the last good pose failed (%s); restarting from this keyframe",
                        self.k, " ".join(str(err).split())[:200])
            try:
                self.restart_window(fo, None, T_guess, with_previous=False)
            except RuntimeError as err2:
                raise WindowVOError(f"the smoother could not restart at keyframe {self.k} (frame "
                                    f"{fo.frame_index}): {' '.join(str(err2).split())[:200]}") from None

    def restart_window(self, fo: FrontendOutput, odom, T_guess: np.ndarray, with_previous: bool) -> None:
        k = self.k
        self._new_smoother()
        self.lm.restart(k, fo.track_ids, fo.pixels_undistorted, fo.pixel_sigma_scale)
        self.floor.floor_frames.clear()  # the fresh smoother holds none
        self.floor.depth.reset()
        self.climb.last = None  # nor the last wheel step's keyframe (tied again below when with_previous)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {}
        self.wheel.forget_failed_start(self.k)
        if with_previous:
            T_prev = self.kf_pose.get(k - 1, np.eye(4))
            graph.add(fac.reset_prior(X(k - 1), T_prev, self.cfg))
            values.insert(X(k - 1), gtsam.Pose3(T_prev))
            stamps[X(k - 1)] = float(k - 1)
            self.wheel.restart_from_previous(graph, values, stamps, k)
            self._motion_factors(graph, values, stamps, k, odom, T_guess, restart=True)
        else:
            graph.add(fac.first_pose_prior(X(k), T_guess))
            self.wheel.restart_here(graph, values, stamps, k)
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


# A keyframe's estimated rotation must be one to this tolerance (|R^T R - I|, max entry): no run of the scale suite
# or the benchmark comes near it; a solve that ran off gave 1.7e-6 growing 2.4x a keyframe, then 1e-226 matrices.
ROTATION_TOLERANCE = 1e-6


def diverged_keyframe(estimate: gtsam.Values, keyframes) -> int | None:
    """The first of ``keyframes`` whose pose in ``estimate`` is not finite or whose rotation is no rotation
    (every window pose after every update: checked at once, about 0.05 ms)."""
    kfs = [int(kk) for kk in keyframes if estimate.exists(X(kk))]
    if not kfs:
        return None
    T = np.stack([estimate.atPose3(X(kk)).matrix() for kk in kfs])
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = ~np.all(np.isfinite(T), axis=(1, 2)) | ~(err <= ROTATION_TOLERANCE) | ~(np.linalg.det(R) > 0.0)
    return kfs[int(np.argmax(bad))] if bad.any() else None


def late_metric_start(be: SlidingWindowBackend, fo: FrontendOutput) -> dict[int, np.ndarray] | None:
    """A monocular run with no floor in its first two keyframes is up to scale until the floor comes into
    view (``FloorModel.late_metric_start``). Then every keyframe pose is rescaled about the first camera
    centre, the window restarts from this keyframe (metric now, so the ground factors hold the scale from
    here on), and the run is metric. Returns the rescaled poses of the keyframes before the window (the
    window's go out as usual), or None when the run stays up to scale."""
    s = be.floor.late_metric_start(be.k)
    if s is None:
        return None
    c0 = (be.kf_pose[0] @ be.T_base_cam)[:3, 3]
    base_from_cam = inv_T(be.T_base_cam)
    for kk, T_wb in be.kf_pose.items():
        T_wc = T_wb @ be.T_base_cam
        T_wc[:3, 3] = c0 + s * (T_wc[:3, 3] - c0)
        be.kf_pose[kk] = T_wc @ base_from_cam
    be.restart_window(fo, None, be.kf_pose[be.k], with_previous=False)
    log.info("keyframe %d (frame %d): the floor is in view; the run is metric from here (scale x %.3f), the "
             "trajectory so far rescaled", be.k, fo.frame_index, s)
    return {be.kf_frame[kk]: be.kf_pose[kk] for kk in range(be.window_start()) if kk in be.kf_pose}


def keyframe_output(be: SlidingWindowBackend, fo: FrontendOutput, n_new: int, n_vis: int, n_ground: int,
                    status: BackendStatus) -> BackendOutput:
    """What the back end hands on after keyframe ``be.k``: the window's poses, the landmarks, the counts, and the
    floor's and the wheel calibration's state."""
    assert be.estimate is not None
    ids, pts = be.lm.positions()
    _, p_seen, uv = be.lm.seen_now(fo.track_ids, fo.pixels_undistorted, be.k)
    rms = reprojection_rms(reprojection_errors(be.camera, be.kf_pose[be.k], be.T_base_cam, p_seen, uv))
    w0 = be.window_start()
    floor, calib = be.floor, be.wheel.calib
    fa = floor.floor_attitude
    tilt = fa.tilt_deg() if fa.ready else (float("nan"), float("nan"))
    return BackendOutput(
        frame_index=fo.frame_index,
        timestamp=fo.timestamp,
        T_world_base=be.kf_pose[be.k].copy(),
        keyframe_poses={be.kf_frame[kk]: be.kf_pose[kk] for kk in range(w0, be.k + 1)},
        p_world_landmarks=pts,
        landmark_ids=ids,
        n_landmarks=len(ids),
        n_new_landmarks=n_new,
        n_vision_factors=n_vis,
        reprojection_rms_px=rms,
        status=status,
        n_ground_factors=n_ground,
        base_rocking_deg=floor.base_rocking_deg,
        level_frame=floor.level_frame,
        floor_tilt_x_deg=tilt[0],
        floor_tilt_y_deg=tilt[1],
        floor_tilt_se_deg=fa.standard_error_deg() if fa.ready else float("nan"),
        floor_normal_learnt=floor.floor_normal_learnt,
        cue_disagreement=float("nan") if floor.last_agreement is None else floor.last_agreement.disagreement,
        cues_agree=None if floor.last_agreement is None else floor.last_agreement.agree,
        wheel_step_sigmas=float("nan") if be.slip.last is None else be.slip.last.sigmas,
        wheel_slip=None if be.slip.last is None else be.slip.last.switched,
        road_step_ratio=be.road.ratio,
        road_pitch_deg=be.road.pitch_deg,
        wheel_scale=calib.scale if be.calibrate else float("nan"),
        wheel_yaw_bias_per_m=calib.yaw_bias_per_m if be.calibrate else float("nan"),
        wheel_yaw_scale=calib.yaw_scale if be.calibrate else float("nan"),
    )
