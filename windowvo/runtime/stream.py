"""The streaming odometry API: feed wheel samples and frames, get each frame's pose at its own time.

::

    camera = read_camera_yaml("camera.yaml")       # windowvo.io.sequence; str or Path
    vo = windowvo.Odometry(camera, config)        # or windowvo.Odometry.from_config("robot.yaml", camera)
    vo.add_wheel_odometry(t, x, y, yaw)            # any rate, any time before the frame
    est = vo.process(t, image)                     # FrameEstimate: T_world_base at t, status, keyframe flag, ...
    vo.smoothed_trajectory()                       # the fixed-lag smoothed poses so far

One code path: the file pipeline (``runtime/pipeline.py``) drives this same object, feeding each
frame's wheel samples just before the frame, so ``trajectory_online.txt`` is exactly what a robot
calling :meth:`Odometry.process` in its loop would have had.

The wheels' own clock may be ahead of or behind the camera's: the offset is estimated from the turns and the
speed changes (``backend/wheel_clock.py``; each frame's image motion goes to it) and, once the data tell it from none, the wheels are read at camera time plus that
offset (``backend.odometry.time_offset``; :meth:`Odometry.wheels_on_camera_clock`).

The causal pose of a frame is the newest keyframe estimate as it was right after that keyframe
was added, moved on to the frame's time by the wheels (their step corrected by the online calibration as that
keyframe's result gave it). Without wheels it is moved on along the window's
last keyframe step (constant velocity), by the share of that step the frame has come: its parallax to the
newest keyframe over that keyframe's own parallax to the one before (``motion_share``; a standstill has
none, so the pose holds). The smoothed
trajectory refines every keyframe with up to ``backend.window_keyframes`` later ones and places
frames between keyframes along the keyframe segment.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..backend.report import ScaleReport, plan_scale
from ..backend.wheel_clock import ClockEstimate, WheelClock
from ..camera import CameraModel
from ..config import Config, DetectionOrder, WheelClockMode, load_robot_config, robot_config_from_dict
from ..errors import WindowVOError
from ..frontend.frontend import Frontend
from ..frontend.tracker import resolve_detection_order
from ..geometry import interpolate_T, inv_T
from ..io.odometry import WheelBuffer, WheelOdometry
from ..io.trajectory import Trajectory
from ..types import BackendOutput, BackendStatus, Frame, FrameEstimate, FrontendOutput, OdometryStep, WheelCalibration

if TYPE_CHECKING:  # GTSAM is loaded only where a back end runs: a pipelined run's main process never needs it
    from ..backend.smoother import SlidingWindowBackend

log = logging.getLogger(__name__)

# Wheel clock: vision's heading change is taken over at least this span (s), from a chain of at most CLOCK_CHAIN
# keyframes; every interval of the run is kept (the offset of two drivers' clocks is constant).
CLOCK_SPAN_S = 1.0
CLOCK_CHAIN = 200
CLOCK_INTERVALS = 100_000
# The offset is re-estimated (and the one applied to the wheel readings updated) every this many new intervals.
CLOCK_UPDATE_EVERY = 10
# ... or every this many new frames with the image's motion (its speed changes: a stop shows the offset at once)
CLOCK_UPDATE_FLOW_FRAMES = 20
# Without wheels a frame's causal pose moves along the last keyframe step by its share of it (parallax over the
# keyframe's own): not beyond this many steps, and held when the keyframe's own parallax was below this (px; a
# keyframe made by time or track loss at a standstill says nothing of a step).
MOTION_SHARE_MAX = 2.0
MOTION_SHARE_MIN_PARALLAX_PX = 2.0


def _calibration(bo: BackendOutput) -> WheelCalibration | None:
    """The online wheel calibration a keyframe's result carries (None: not estimated yet)."""
    c = (bo.wheel_scale, bo.wheel_yaw_bias_per_m, bo.wheel_yaw_scale)
    if not all(np.isfinite(c)):
        return None
    return WheelCalibration(scale=c[0], yaw_bias_per_m=c[1], yaw_scale=c[2])


def _last_step(bo: BackendOutput) -> np.ndarray | None:
    """T_base(k-1)_base(k) of the window's two newest keyframes as this result gives them (None: one keyframe)."""
    frames = sorted(bo.keyframe_poses)
    if len(frames) < 2:
        return None
    return inv_T(bo.keyframe_poses[frames[-2]]) @ bo.keyframe_poses[frames[-1]]


@dataclass
class TrackedFrame:
    """A frame through the front end, waiting for its keyframe's back-end result (or for earlier ones)."""

    index: int
    timestamp: float
    t_in: float  # perf_counter when the frame came in (latency)
    frontend: FrontendOutput | None  # None for a skipped frame
    odom: OdometryStep | None  # wheel step since the previous keyframe (keyframes only)
    note: str = ""
    wheel_delta: np.ndarray | None = None  # T_base(last keyframe)_base(this frame) from the wheels, at tracking time
    wheel_distance_m: float = 0.0  # the wheels' distance since the last keyframe, at tracking time
    # Without wheels: how far along a step like the newest keyframe's own this frame has come (its parallax to that
    # keyframe over the keyframe's parallax to the one before, at tracking time; None: no share known).
    motion_share: float | None = None

    @property
    def is_keyframe(self) -> bool:
        return self.frontend is not None and self.frontend.is_keyframe


def _new_backend(camera: CameraModel, cfg: Config, use_odometry: bool) -> SlidingWindowBackend:
    from ..backend.smoother import SlidingWindowBackend

    return SlidingWindowBackend(camera, cfg.backend, use_odometry)


def default_config() -> Config:
    """The default configuration, for callers that have no config file (no sequence, no output)."""
    return robot_config_from_dict({})


class Odometry:
    """Visual-wheel odometry fed one frame (and any number of wheel samples) at a time.

    It runs its own back end (``backend``, built here when not given) unless ``remote_backend``: then the
    caller runs the keyframes elsewhere (the pipelined mode's worker process builds that back end) and hands
    each result to :meth:`resolve`, and the final :class:`ScaleReport` to :attr:`remote_report`."""

    def __init__(self, camera: CameraModel, config: Config | None = None, use_wheels: bool = True,
                 static_mask: np.ndarray | None = None, wheel_comment: str = "",
                 backend: SlidingWindowBackend | None = None, remote_backend: bool = False):
        cfg = config if config is not None else default_config()
        self.cfg = cfg
        self.camera = camera
        self.use_odometry = bool(use_wheels and cfg.backend.use_odometry)
        self.plan = plan_scale(camera, cfg.backend, self.use_odometry)
        self.backend: SlidingWindowBackend | None = None
        if not remote_backend:
            self.backend = backend if backend is not None else _new_backend(camera, cfg, self.use_odometry)
        floor_only = self.plan.use_ground and not self.use_odometry  # the floor is the only scale source
        order = resolve_detection_order(cfg.frontend.detection_order, floor_only)
        # With wheels and the floor, rows first unless the base rocks on its suspension (frontend/rocking.py).
        rocking_switch = cfg.frontend.detection_order is DetectionOrder.AUTO and self.plan.use_ground and not floor_only
        self.frontend = Frontend(camera, cfg.frontend.model_copy(update={"detection_order": order}), cfg.keyframes,
                                 cfg.gates, static_mask, rocking_switch)
        self.wheels = WheelBuffer(extrapolate_s=cfg.backend.odometry.max_gap_s, comment=wheel_comment)
        self.wheels.max_speed_m_s = cfg.backend.odometry.max_speed_m_s
        # The wheels' clock against the camera's, from vision's heading changes over CLOCK_SPAN_S; the wheels are read
        # at camera time t + wheel_offset_s (backend.odometry.time_offset), from the time offset_applied_since.
        self.clock = WheelClock(window=CLOCK_INTERVALS) if self.use_odometry else None
        odo_cfg = cfg.backend.odometry
        self.clock_mode = odo_cfg.time_offset
        fixed = self.clock_mode is WheelClockMode.FIXED
        self.wheel_offset_s = odo_cfg.time_offset_ms / 1000.0 if fixed else 0.0
        self.offset_applied_since: float | None = None
        self._clock_updated_at = 0  # the clock's interval count at the last re-estimate
        self._clock_flows_at = 0  # ... and its count of frame intervals with the image's motion
        self._shifted: tuple[WheelOdometry, float, WheelOdometry] | None = None  # (raw view, offset, shifted view)
        self._vision_yaw: list[tuple[float, float]] = []  # (keyframe time, heading chained from two-view rotations)
        self._last_frontend_t: float | None = None  # the time of the last frame the front end tracked
        self.frames: list[tuple[int, float]] = []  # (frame index, timestamp) of every frame, skipped ones too
        self.online: list[np.ndarray] = []  # causal T_world_base per frame
        self.kf_frames: list[int] = []
        self.kf_times: list[float] = []
        self.last_kf_time: float | None = None
        self.last_kf_online: np.ndarray | None = None  # newest keyframe pose as estimated when it was added
        # Without wheels: the window's last keyframe step (T_base(k-1)_base(k), smoothed, as the newest result gave
        # it), the newest keyframe's parallax to the one before, and the last tracked frame's share of that step.
        self.kf_step: np.ndarray | None = None
        self.wheel_calibration: WheelCalibration | None = None  # the newest result's online calibration (None: none)
        self._kf_step_parallax: float | None = None
        self._last_share: float | None = None
        self.kf_pose_by_frame: dict[int, np.ndarray] = {}  # latest smoothed T_world_base per keyframe
        # Keyframes whose wheel step the back end took for slip (backend/wheel_slip.py): the wheel samples within
        # that step do not tell where the frames between the two keyframes were.
        self.slipped_kf_frames: set[int] = set()
        self.notes: list[str] = []
        self._n_tracked = 0
        self._last_t: float | None = None
        self.remote_report: ScaleReport | None = None  # scale report of a back end run elsewhere (parallel.py)

    @classmethod
    def from_config(cls, config: Config | str | Path, camera: CameraModel, use_wheels: bool = True) -> Odometry:
        """From a validated config or a robot's YAML file (``str`` or ``Path``; read by
        :func:`windowvo.config.load_robot_config`: no ``sequence`` or ``output`` needed, unused when present)."""
        cfg = config if isinstance(config, Config) else load_robot_config(config)
        return cls(camera, cfg, use_wheels)

    # ------------------------------------------------------------------ inputs
    def add_wheel_odometry(self, t: float, x: float, y: float, yaw: float) -> None:
        """One wheel-odometry sample: planar pose of the base in the odometry frame at time t (s)."""
        self.wheels.append(t, x, y, yaw)

    def wheels_on_camera_clock(self) -> WheelOdometry | None:
        """The wheel samples so far as this odometry reads them: on the camera's clock, shifted by the offset
        applied (``backend.odometry.time_offset``); None without wheels in use."""
        return self._camera_clock_wheels() if self.use_odometry else None

    def _camera_clock_wheels(self) -> WheelOdometry | None:
        """The same for every sample fed (the standstill check reads them with or without wheel factors)."""
        raw = self.wheels.view()
        if raw is None or self.wheel_offset_s == 0.0:
            return raw
        if self._shifted is None or self._shifted[0] is not raw or self._shifted[1] != self.wheel_offset_s:
            self._shifted = (raw, self.wheel_offset_s, raw.on_camera_clock(self.wheel_offset_s))
        return self._shifted[2]

    def process(self, t: float, image: np.ndarray, index: int | None = None, mask: np.ndarray | None = None,
                is_last: bool = False) -> FrameEstimate:
        """Track one grayscale uint8 frame taken at time t; returns its causal pose.

        ``index`` defaults to the count of frames so far; ``is_last`` makes it a keyframe (end of a run)."""
        tracked = self.track(t, image, index, mask, is_last)
        return self.resolve(tracked, self.run_backend(tracked))

    def run_backend(self, tracked: TrackedFrame) -> BackendOutput | None:
        """The back end's result for a keyframe, in this process (None for other frames)."""
        if tracked.frontend is None or not tracked.frontend.is_keyframe:
            return None
        if self.backend is None:
            raise WindowVOError("this Odometry has no back end of its own (remote_backend=True)")
        return self.backend.add_keyframe(tracked.frontend, tracked.odom)

    def skip(self, index: int, t: float, reason: str) -> FrameEstimate:
        """A frame that could not be used (black, duplicate, unreadable): it still gets a pose."""
        return self.resolve(self.track_skipped(index, t, reason), None)

    # The two halves of ``process``, for callers that run the back end elsewhere (``parallel.py``):
    # ``track`` runs the front end and takes every wheel reading the frame's pose will need, so
    # ``resolve`` gives the same causal pose however late the keyframe's back-end result comes.
    def track(self, t: float, image: np.ndarray, index: int | None = None, mask: np.ndarray | None = None,
              is_last: bool = False) -> TrackedFrame:
        t_in = time.perf_counter()
        if image is None or image.ndim != 2 or image.dtype != np.uint8:
            raise WindowVOError("Odometry.process needs a grayscale uint8 image (H x W)")
        if image.shape != (self.camera.height, self.camera.width):
            raise WindowVOError(f"image is {image.shape[1]}x{image.shape[0]}, the camera "
                                f"{self.camera.width}x{self.camera.height}")
        if self._last_t is not None and t <= self._last_t:
            raise WindowVOError(f"frame times must increase: {t} after {self._last_t}")
        idx = self._n_tracked if index is None else index
        if self.offset_applied_since is None and self.clock_mode is WheelClockMode.FIXED:
            self.offset_applied_since = float(t)
        frame = Frame(idx, float(t), image, mask)
        fo = self.frontend.process(frame, self._odom_since_kf(t), force_keyframe=is_last)
        if self.clock is not None and self._last_frontend_t is not None:  # the image's motion since the frame before
            self.clock.add_flow(self._last_frontend_t, float(t), fo.flow_px)
        self._last_frontend_t = float(t)
        odom, note = None, self.frontend.rocking_note
        if note:
            self.notes.append(note)
            self.frontend.rocking_note = ""
        if fo.is_keyframe:
            if self.cfg.backend.ground.road_region.enabled:  # a copy: the caller may reuse its buffer
                fo.image, fo.image_mask = image.copy(), self.frontend.mask_of(frame)
            self._observe_clock(fo, float(t))
            self._update_offset(float(t))
            odom = self._odom_step(self.last_kf_time, t) if self.last_kf_time is not None else None
            if odom is not None and not odom.ok:
                note = _join_notes(note, "odometry gap: vision only")
            self.kf_frames.append(idx)
            self.kf_times.append(float(t))
            self.last_kf_time = float(t)
        return self._tracked(TrackedFrame(idx, float(t), t_in, fo, odom, note))

    def _observe_clock(self, fo: FrontendOutput, t: float) -> None:
        """Chain vision's heading changes between keyframes (the front end's two-view rotations, no wheels in them)
        and give the wheel clock the change over the last ``CLOCK_SPAN_S``; a keyframe without one restarts it."""
        if self.clock is None:
            return
        if self.last_kf_time is None or fo.R_cam_kf_cam is None or not self._vision_yaw:
            self._vision_yaw = [(t, 0.0)]
            return
        R_bc = self.camera.T_base_cam[:3, :3]
        R = R_bc @ fo.R_cam_kf_cam.T @ R_bc.T  # base rotation from the last keyframe to this one
        self._vision_yaw.append((t, self._vision_yaw[-1][1] + float(np.arctan2(R[1, 0], R[0, 0]))))
        for t0, yaw0 in reversed(self._vision_yaw[:-1]):
            if t - t0 >= CLOCK_SPAN_S:
                self.clock.add(t0, t, self._vision_yaw[-1][1] - yaw0)
                break
        del self._vision_yaw[:-CLOCK_CHAIN]

    def _update_offset(self, t: float) -> None:
        """Re-estimate the offset every CLOCK_UPDATE_EVERY new intervals (from the wheel samples so far: causal) and,
        with ``time_offset: estimate``, read the wheels at the new estimate from now on once it is observable and told from a zero offset."""
        raw = self.wheels.view()
        if self.clock is None or raw is None:
            return
        if (self.clock.n_added - self._clock_updated_at < CLOCK_UPDATE_EVERY
                and self.clock.n_flows_added - self._clock_flows_at < CLOCK_UPDATE_FLOW_FRAMES):
            return
        self._clock_updated_at = self.clock.n_added
        self._clock_flows_at = self.clock.n_flows_added
        est = self.clock.update(raw)
        if (est.observable and est.zero_rejected and math.isfinite(est.offset_s)
                and self.clock_mode is WheelClockMode.ESTIMATE):
            self.wheel_offset_s = est.offset_s
            if self.offset_applied_since is None:
                self.offset_applied_since = t

    def wheel_time_offset(self) -> ClockEstimate | None:
        """The wheels' time offset to the camera (``t_wheels = t_camera + offset_s``) from the keyframes so far, with
        the offset applied to the wheel readings (``applied_s``, None when none was); None without wheels."""
        raw = self.wheels.view() if self.use_odometry else None
        if self.clock is None or raw is None:
            return None
        applied = self.offset_applied_since is not None
        return replace(self.clock.update(raw), applied_s=self.wheel_offset_s if applied else None,
                       applied_since_t=self.offset_applied_since)

    def track_skipped(self, index: int, t: float, reason: str) -> TrackedFrame:
        return self._tracked(TrackedFrame(index, float(t), time.perf_counter(), None, None, f"skipped: {reason}"))

    def _tracked(self, tr: TrackedFrame) -> TrackedFrame:
        self._n_tracked += 1
        self._last_t = tr.timestamp
        odo = self.wheels_on_camera_clock()
        if self.last_kf_time is not None:
            tr.wheel_delta = np.eye(4)
            if odo is not None and tr.timestamp > self.last_kf_time:
                tr.wheel_delta = odo.delta(self.last_kf_time, tr.timestamp)
                tr.wheel_distance_m = odo.distance(self.last_kf_time, tr.timestamp)
        if odo is None:
            tr.motion_share = self._motion_share(tr.frontend)
        return tr

    def _motion_share(self, fo: FrontendOutput | None) -> float | None:
        """Without wheels, the share of the newest keyframe's step a frame has come (see ``TrackedFrame``); a skipped
        frame keeps the last tracked frame's, a keyframe starts its own step."""
        if fo is None:
            return self._last_share
        if fo.is_keyframe:
            self._kf_step_parallax = fo.parallax_px
            share: float | None = 0.0
        elif self._kf_step_parallax is None or not self._kf_step_parallax >= MOTION_SHARE_MIN_PARALLAX_PX:
            share = None
        else:
            share = float(np.clip(fo.parallax_px / self._kf_step_parallax, 0.0, MOTION_SHARE_MAX))
        self._last_share = share
        return share

    def resolve(self, tr: TrackedFrame, bo: BackendOutput | None) -> FrameEstimate:
        """Apply a keyframe's back-end result (frames in order) and give the frame its causal pose."""
        note = tr.note
        if bo is not None:
            self.last_kf_online = bo.T_world_base.copy()
            self.kf_step = _last_step(bo)
            self.wheel_calibration = _calibration(bo)
            self.kf_pose_by_frame.update(bo.earlier_keyframe_poses)
            self.kf_pose_by_frame.update(bo.keyframe_poses)
            if bo.wheel_slip:
                self.slipped_kf_frames.add(bo.frame_index)
            if bo.status is BackendStatus.RECOVERED:
                note = _join_notes(note, "backend reset")
            if bo.metric_start:
                note = _join_notes(note, "metric from here (the floor came into view; trajectory so far rescaled)")
        if self.last_kf_online is None or tr.wheel_delta is None:
            T = np.eye(4)
        elif tr.motion_share is not None and self.kf_step is not None:  # no wheels: along the last keyframe step
            T = self.last_kf_online @ interpolate_T(np.eye(4), self.kf_step, tr.motion_share)
        elif self.wheel_calibration is not None:  # the wheels' step less their systematic errors
            T = self.last_kf_online @ self.wheel_calibration.correct(tr.wheel_delta, tr.wheel_distance_m)
        else:
            T = self.last_kf_online @ tr.wheel_delta
        self.frames.append((tr.index, tr.timestamp))
        self.online.append(T)
        fo = tr.frontend
        if fo is None:
            return FrameEstimate(tr.index, tr.timestamp, T, skipped=True, note=note)
        return FrameEstimate(tr.index, tr.timestamp, T, fo.is_keyframe, False, bo.status if bo is not None else None,
                             (time.perf_counter() - tr.t_in) * 1000.0, fo, bo, note)

    # ------------------------------------------------------------------ wheel helpers
    def _odom_since_kf(self, t: float) -> tuple[float, float] | None:
        """Distance and absolute turn since the last keyframe (the front end's standstill check)."""
        odo = self._camera_clock_wheels()
        if odo is None or self.last_kf_time is None:
            return None
        d = odo.delta(self.last_kf_time, t)
        return float(np.hypot(d[0, 3], d[1, 3])), abs(float(np.arctan2(d[1, 0], d[0, 0])))

    def _odom_step(self, t0: float, t1: float) -> OdometryStep | None:
        odo = self.wheels_on_camera_clock()
        if not self.use_odometry:
            return None
        if odo is None:
            msg = f"no wheel odometry yet at t={t1:.3f} s; vision only for that step"
            log.warning(msg)
            self.notes.append(msg)
            return OdometryStep(np.eye(4), 0.0, False)
        ok = odo.covers(t0) and odo.covers(t1) and odo.max_gap_in(t0, t1) <= self.cfg.backend.odometry.max_gap_s
        if not ok:
            msg = f"odometry missing or stale between t={t0:.3f} and t={t1:.3f} s; vision only for that step"
            log.warning(msg)
            self.notes.append(msg)
        return OdometryStep(odo.delta(t0, t1), odo.distance(t0, t1), ok)

    # ------------------------------------------------------------------ outputs
    def online_trajectory(self) -> Trajectory:
        """The causal pose of every frame so far (what the robot had at each frame's time)."""
        if not self.frames:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.asarray([t for _, t in self.frames]), np.stack(self.online))

    def smoothed_trajectory(self) -> Trajectory:
        """One pose per frame: keyframes from the smoother, the others in between.

        Frames between two keyframes are placed along the segment joining them, at the fraction of
        wheel distance (or time, without wheels, or where the back end took the step's wheels for slip) covered
        so far; frames after the last keyframe follow the wheels (or stay at the last keyframe)."""
        # Keyframes whose back-end result never came (a run aborted at once) are left out.
        done = [(f, t) for f, t in zip(self.kf_frames, self.kf_times) if f in self.kf_pose_by_frame]
        kf_f = [f for f, _ in done]
        if not done:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        kf_poses = [self.kf_pose_by_frame[f] for f, _ in done]
        kf_t = np.asarray([t for _, t in done])
        odo = self.wheels_on_camera_clock()
        ts, poses = [], []
        for _, t in self.frames:
            j = int(np.searchsorted(kf_t, t, side="right")) - 1
            if j < 0:
                T = kf_poses[0]
            elif j >= len(kf_t) - 1 or t == kf_t[j]:
                T = kf_poses[j]
                if t > kf_t[j] and odo is not None:
                    T = T @ odo.delta(kf_t[j], t)
            else:
                t0, t1 = kf_t[j], kf_t[j + 1]
                s = (t - t0) / (t1 - t0)
                if odo is not None and kf_f[j + 1] not in self.slipped_kf_frames:
                    total = odo.distance(t0, t1)
                    if total > 1e-3:
                        s = odo.distance(t0, t) / total
                T = interpolate_T(kf_poses[j], kf_poses[j + 1], float(np.clip(s, 0.0, 1.0)))
            ts.append(t)
            poses.append(T)
        return Trajectory(np.asarray(ts), np.stack(poses))

    def scale_report(self) -> ScaleReport:
        """Whether the run is metric, what fixed its scale, the final wheel calibration, the resets."""
        if self.remote_report is not None:
            return self.remote_report
        if self.backend is None:
            return ScaleReport.lost(self.use_odometry)
        return self.backend.scale_report()


def _join_notes(note: str, more: str) -> str:
    return f"{note}; {more}" if note else more
