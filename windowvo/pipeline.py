"""The pipeline: data provider -> front end -> back end -> outputs and viewer, sequentially.

Runs deterministically in one thread. Whatever happens (a failing frame, Ctrl-C, SIGTERM),
the trajectory of every frame processed so far, ``stats.csv`` and the recording are written.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import logging
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .backend.smoother import SlidingWindowBackend, WheelCalibration
from .config import Config, save_config
from .errors import SequenceError
from .frontend.frontend import Frontend
from .geometry import interpolate_T
from .io.provider import DataProvider, SkippedFrame
from .io.sequence import Sequence
from .io.trajectory import Trajectory, write_tum
from .types import BackendOutput, BackendStatus, FrameEstimate, FrameRecord, FrontendOutput, OdometryStep

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    n_frames: int
    n_keyframes: int
    n_skipped: int
    wall_s: float
    trajectory: Trajectory
    records: list[FrameRecord]
    monocular: bool
    interrupted: bool = False
    frontend_ms: list[float] = field(default_factory=list)
    backend_ms: list[float] = field(default_factory=list)
    n_resets: int = 0
    notes: list[str] = field(default_factory=list)
    last_frame_index: int = -1
    metric: bool = False  # the scale is metric (wheels, or the ground plane at the camera height)
    scale_sources: list[str] = field(default_factory=list)
    wheel_calibration: WheelCalibration | None = None  # final online estimate (with wheels)
    trajectory_online: Trajectory | None = None  # causal pose per frame, as a robot had it at that time

    @property
    def fps(self) -> float:
        return self.n_frames / self.wall_s if self.wall_s > 0 else 0.0


def load_static_mask(path: Path | None, shape: tuple[int, int]) -> np.ndarray | None:
    if path is None:
        return None
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise SequenceError(f"mask image not readable: {path}")
    if m.shape != shape:
        raise SequenceError(f"mask {path.name} is {m.shape[1]}x{m.shape[0]}, images are {shape[1]}x{shape[0]}")
    return m


class Pipeline:
    def __init__(self, cfg: Config, seq: Sequence, viewer=None, progress: Callable | None = None):
        self.cfg = cfg
        self.seq = seq
        self.viewer = viewer
        self.progress = progress
        cam = seq.camera
        self.use_odometry = cfg.backend.use_odometry and seq.odometry is not None
        self.frontend = Frontend(cam, cfg.frontend, cfg.keyframes, cfg.gates,
                                 load_static_mask(cfg.frontend.mask, (cam.height, cam.width)))
        self.backend = SlidingWindowBackend(cam, cfg.backend, self.use_odometry)
        self.provider = DataProvider(seq, cfg.checks, cfg.max_frames, cfg.frontend.mask_folder)
        # Per processed or skipped frame: (frame index, timestamp); keyframe poses by frame index.
        self.frames: list[tuple[int, float]] = []
        self.kf_frames: list[int] = []
        self.kf_times: list[float] = []
        self.records: list[FrameRecord] = []
        self.last_kf_time: float | None = None
        self.last_kf_online: np.ndarray | None = None  # newest keyframe pose as estimated when it was added
        self.online: list[np.ndarray] = []  # causal T_world_base per processed or skipped frame
        self.notes: list[str] = []

    # ------------------------------------------------------------------ odometry helpers
    def _odom_since_kf(self, t: float) -> tuple[float, float] | None:
        odo = self.seq.odometry
        if odo is None or self.last_kf_time is None:
            return None
        d = odo.delta(self.last_kf_time, t)
        return float(np.hypot(d[0, 3], d[1, 3])), abs(float(np.arctan2(d[1, 0], d[0, 0])))

    def _odom_step(self, t0: float, t1: float) -> OdometryStep | None:
        odo = self.seq.odometry
        if odo is None or not self.use_odometry:
            return None
        ok = odo.covers(t0) and odo.covers(t1) and odo.max_gap_in(t0, t1) <= self.cfg.backend.odometry.max_gap_s
        if not ok:
            msg = f"odometry missing or stale between t={t0:.3f} and t={t1:.3f} s; vision only for that step"
            log.warning(msg)
            self.notes.append(msg)
        return OdometryStep(odo.delta(t0, t1), odo.distance(t0, t1), ok)

    # ------------------------------------------------------------------ main loop
    def run(self) -> RunResult:
        """Process every frame. Ctrl-C and SIGTERM stop the run between two frames, so the
        outputs always describe whole frames; a second Ctrl-C aborts at once."""
        t_start = time.perf_counter()
        stop = {"signal": None}

        def on_signal(signum, frame):
            if stop["signal"] is not None and signum == signal.SIGINT:
                raise KeyboardInterrupt
            stop["signal"] = signum

        previous = {}
        for sig in (signal.SIGTERM, signal.SIGINT):
            # Not in the main thread: no handlers, Ctrl-C raises as usual.
            with contextlib.suppress(ValueError):
                previous[sig] = signal.signal(sig, on_signal)
        n_total = len(self.provider)
        interrupted = False
        try:
            for item in self.provider:
                self._step(item, item.index == n_total - 1)
                if self.progress is not None:
                    self.progress(len(self.frames), len(self.kf_frames))
                if stop["signal"] is not None:
                    break
        except KeyboardInterrupt:
            interrupted = True
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if stop["signal"] is not None or interrupted:
            interrupted = True
            last = self.frames[-1][0] if self.frames else -1
            log.warning("interrupted after frame %d: writing the results so far", last)
        wall = time.perf_counter() - t_start
        traj = self.assemble_trajectory()
        return RunResult(
            n_frames=len(self.frames),
            n_keyframes=len(self.kf_frames),
            n_skipped=sum(1 for r in self.records if r.note.startswith("skipped")),
            wall_s=wall,
            trajectory=traj,
            records=self.records,
            monocular=not self.use_odometry,
            interrupted=interrupted,
            frontend_ms=[r.frontend_ms for r in self.records if r.frontend_ms > 0],
            backend_ms=[r.backend_ms for r in self.records if r.is_keyframe],
            n_resets=self.backend.n_resets,
            notes=self.notes,
            last_frame_index=self.frames[-1][0] if self.frames else -1,
            **self.scale_report(),
            trajectory_online=self.online_trajectory(),
        )

    def _step(self, item, is_last: bool) -> None:
        t_in = time.perf_counter()
        if isinstance(item, SkippedFrame):
            log.warning("skipping %s", item.reason)
            note = f"skipped: {item.reason}"
            self.frames.append((item.index, item.timestamp))
            self.online.append(self._online_pose(item.timestamp))
            self.records.append(FrameRecord(item.index, item.timestamp, 0, 0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, False,
                                            "", "", "", 0, float("nan"), 0.0, 0.0, note=note))
            return
        frame = item
        fo = self.frontend.process(frame, self._odom_since_kf(frame.timestamp), force_keyframe=is_last)
        bo: BackendOutput | None = None
        note = ""
        if fo.is_keyframe:
            odom = None
            if self.last_kf_time is not None:
                odom = self._odom_step(self.last_kf_time, frame.timestamp)
            if odom is not None and not odom.ok:
                note = "odometry gap: vision only"
            bo = self.backend.add_keyframe(fo, odom)
            self.kf_frames.append(frame.index)
            self.kf_times.append(frame.timestamp)
            self.last_kf_time = frame.timestamp
            self.last_kf_online = bo.T_world_base.copy()
            if bo.status is BackendStatus.RECOVERED:
                note = (note + "; " if note else "") + "backend reset"
        T_online = self._online_pose(frame.timestamp)
        # The frame counts as processed only once everything about it is known (an interrupt
        # in the middle leaves frames and records in step).
        self.frames.append((frame.index, frame.timestamp))
        self.online.append(T_online)
        latency_ms = (time.perf_counter() - t_in) * 1000.0
        self.records.append(self._record(fo, bo, note, latency_ms))
        if self.viewer is not None:
            est = FrameEstimate(frame.index, frame.timestamp, T_online, fo.is_keyframe, False,
                                bo.status if bo is not None else None, latency_ms, fo, bo, note)
            self.viewer.log_frame(frame, est)

    def _online_pose(self, t: float) -> np.ndarray:
        """Causal pose at time t: the newest keyframe estimate as it was when added, moved on by
        the wheels since (held without wheels)."""
        if self.last_kf_online is None or self.last_kf_time is None:
            return np.eye(4)
        odo = self.seq.odometry if self.use_odometry else None
        if odo is not None and t > self.last_kf_time:
            return self.last_kf_online @ odo.delta(self.last_kf_time, t)
        return self.last_kf_online.copy()

    def _record(self, fo: FrontendOutput, bo: BackendOutput | None, note: str, latency_ms: float) -> FrameRecord:
        return FrameRecord(
            frame_index=fo.frame_index,
            timestamp=fo.timestamp,
            n_tracked=len(fo.track_ids) + len(fo.outlier_pixels),
            n_inliers=len(fo.track_ids),
            n_detected=fo.n_detected,
            parallax_px=round(fo.parallax_px, 3),
            rot_comp_parallax_px=round(fo.rot_comp_parallax_px, 3),
            inlier_ratio=round(fo.inlier_ratio, 4),
            cheirality_ratio=round(fo.cheirality_ratio, 4),
            spread=round(fo.spread, 3),
            is_keyframe=fo.is_keyframe,
            keyframe_reason=fo.keyframe_reason.value,
            gate=fo.gate.value if fo.is_keyframe or fo.frame_index == 0 else "",
            backend_status=bo.status.value if bo is not None else "",
            n_landmarks=bo.n_landmarks if bo is not None else 0,
            reprojection_rms_px=round(bo.reprojection_rms_px, 4) if bo is not None else float("nan"),
            frontend_ms=round(fo.frontend_ms, 3),
            backend_ms=round(bo.backend_ms, 3) if bo is not None else 0.0,
            note=note,
            n_ground_factors=bo.n_ground_factors if bo is not None else 0,
            wheel_scale=round(bo.wheel_scale, 5) if bo is not None else float("nan"),
            wheel_yaw_bias_per_m=round(bo.wheel_yaw_bias_per_m, 6) if bo is not None else float("nan"),
            latency_ms=round(latency_ms, 3),
        )

    # ------------------------------------------------------------------ outputs
    def keyframe_pose(self, frame_index: int) -> np.ndarray | None:
        try:
            k = self.kf_frames.index(frame_index)
        except ValueError:
            return None
        return self.backend.kf_pose.get(k)

    def scale_report(self) -> dict:
        """Whether the run is metric, what fixed its scale, and the final wheel calibration."""
        be = self.backend
        return {
            "metric": bool(be.metric),
            "scale_sources": [s.value for s in be.scale_sources()],
            "wheel_calibration": be.calibration_with_sigma() if be.calibrate and be.k >= 0 else None,
        }

    def online_trajectory(self) -> Trajectory:
        """The causal pose of every processed or skipped frame (what the robot had at that frame's time)."""
        if not self.frames:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.asarray([t for _, t in self.frames]), np.stack(self.online))

    def assemble_trajectory(self) -> Trajectory:
        """One pose per frame: keyframes from the smoother, the others in between.

        Frames between two keyframes are placed along the segment joining them, at the
        fraction of wheel distance (or time, without odometry) covered so far; frames after
        the last keyframe follow the wheels (or stay at the last keyframe).
        """
        if not self.frames or not self.kf_frames:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        kf_poses = [self.backend.kf_pose[k] for k in range(len(self.kf_frames))]
        kf_t = np.asarray(self.kf_times)
        odo = self.seq.odometry if self.use_odometry else None
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
                if odo is not None:
                    total = odo.distance(t0, t1)
                    if total > 1e-3:
                        s = odo.distance(t0, t) / total
                T = interpolate_T(kf_poses[j], kf_poses[j + 1], float(np.clip(s, 0.0, 1.0)))
            ts.append(t)
            poses.append(T)
        return Trajectory(np.asarray(ts), np.stack(poses))


def write_outputs(cfg: Config, result: RunResult, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    header = "T_world_base, world = base at the first frame (TUM: t tx ty tz qx qy qz qw)"
    if not result.metric:
        header += "\nmonocular run: translation is up to scale"
    elif result.scale_sources:
        header += "\nmetric scale from: " + ", ".join(result.scale_sources)
    write_tum(out / "trajectory.txt", result.trajectory.timestamps, result.trajectory.T_world_base,
              header="windowvo estimate (fixed-lag smoothed): " + header)
    if result.trajectory_online is not None and len(result.trajectory_online):
        write_tum(out / "trajectory_online.txt", result.trajectory_online.timestamps,
                  result.trajectory_online.T_world_base,
                  header="windowvo causal estimate (each frame's pose as known at that frame's time): " + header)
    write_stats(out / "stats.csv", result.records)
    save_config(cfg, out / "config_resolved.yaml")


def write_stats(path: Path, records: list[FrameRecord]) -> None:
    fields = [f.name for f in dataclasses.fields(FrameRecord)]
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(fields)
        for r in records:
            w.writerow([getattr(r, f) for f in fields])
    tmp.replace(path)
