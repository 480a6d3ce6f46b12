"""The file pipeline: data provider -> streaming odometry (``runtime.stream.Odometry``) -> outputs and viewer.

Runs deterministically in one thread, through the same :class:`~windowvo.stream.Odometry` object a
robot would call in its loop (wheel samples fed up to each frame's time, then the frame). Whatever
happens (a failing frame, Ctrl-C, SIGTERM), the trajectory of every frame processed so far,
``stats.csv`` and the recording are written; on a hard kill (SIGKILL, out of memory) the journal
``journal.jsonl`` (every finished frame's stats row and causal pose, every keyframe's smoothed pose once final)
and the causal trajectory ``trajectory_online.txt``, both appended and flushed at every keyframe, still hold
every frame up to the last finished keyframe (``runtime/journal.py``; ``--resume`` rebuilds the outputs).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..backend.report import ScaleReport
from ..backend.wheel_clock import ClockEstimate
from ..config import Config, RunMode
from ..errors import SequenceError
from ..io.provider import DataProvider, SkippedFrame
from ..io.sequence import Sequence
from ..io.trajectory import Trajectory, TumJournal
from ..types import BackendOutput, Frame, FrameEstimate, FrameRecord, FrontendOutput, WheelCalibration
from . import stop
from .journal import JOURNAL_NAME, RunJournal
from .parallel import MAX_IN_FLIGHT, BackendWorker
from .stream import Odometry, TrackedFrame

log = logging.getLogger(__name__)

# Frames decoded ahead by a thread in pipelined mode.
PREFETCH_FRAMES = 4
ONLINE_HEADER = "windowvo causal estimate (each frame's pose as known at that frame's time)"


@dataclass
class RunResult:
    """What a run computed: the trajectories, one record per frame, timings and the scale report."""

    n_frames: int
    n_keyframes: int
    n_skipped: int
    wall_s: float
    trajectory: Trajectory
    records: list[FrameRecord]
    monocular: bool
    scale: ScaleReport
    interrupted: bool = False
    frontend_ms: list[float] = field(default_factory=list)
    backend_ms: list[float] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    last_frame_index: int = -1
    trajectory_online: Trajectory | None = None  # causal pose per frame, as a robot had it at that time
    wheel_time_offset: ClockEstimate | None = None  # the wheels' clock against the camera's, and what was applied
    # A second pass (backend.odometry.time_offset_second_pass): the first pass's clock estimate (None: one pass)
    first_pass_clock: ClockEstimate | None = None

    @property
    def fps(self) -> float:
        return self.n_frames / self.wall_s if self.wall_s > 0 else 0.0

    # The scale report's fields, read as the run's own.
    @property
    def metric(self) -> bool:
        return self.scale.metric

    @property
    def scale_sources(self) -> list[str]:
        return self.scale.scale_sources

    @property
    def wheel_calibration(self) -> WheelCalibration | None:
        return self.scale.wheel_calibration

    @property
    def metric_from_frame(self) -> int | None:
        return self.scale.metric_from_frame

    @property
    def floor_scale_reanchors(self) -> int:
        return self.scale.floor_scale_reanchors

    @property
    def floor_untied(self) -> int:
        return self.scale.floor_untied

    @property
    def floor_beside_track(self) -> int:
        return self.scale.floor_beside_track

    @property
    def floor_depth_m(self) -> float | None:
        return self.scale.floor_depth_m

    @property
    def n_resets(self) -> int:
        return self.scale.n_resets


def load_static_mask(path: Path | None, shape: tuple[int, int]) -> np.ndarray | None:
    if path is None:
        return None
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise SequenceError(f"mask image not readable: {path}")
    if m.shape != shape:
        raise SequenceError(f"mask {path.name} is {m.shape[1]}x{m.shape[0]}, images are {shape[1]}x{shape[0]}")
    return m


@contextlib.contextmanager
def opencv_threads(n: int) -> Iterator[None]:
    """OpenCV's worker threads set to ``n`` while the block runs, then put back (0: left as they are). The threads
    are the process's: an application that runs windowvo gets its own setting back when the run ends."""
    if n <= 0:
        yield
        return
    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def load_in_background(module: str) -> None:
    """Import ``module`` in a thread of its own while this one waits for something else (the GIL is free then):
    the evaluator's evo and scipy (about 0.4 s) while the back-end process finishes its last keyframes. A failure
    is left to the real import, which raises it where it is used."""

    def load() -> None:
        with contextlib.suppress(Exception):
            importlib.import_module(module)

    threading.Thread(target=load, name="windowvo-preload", daemon=True).start()


class Pipeline:
    """Runs a sequence through the streaming odometry and collects what the outputs need."""

    def __init__(self, cfg: Config, seq: Sequence, viewer=None, progress: Callable | None = None,
                 journal: bool = True, worker: BackendWorker | None = None, continuation: int | None = None):
        """``continuation``: the run continues a killed one (``--resume``) on a sub-sequence from frame
        ``seq.first_frame``, joining it at this frame: its journal lines are appended to the folder's journal as a
        new segment (poses in the continuation's own world, frame indices of the whole sequence), and
        ``trajectory_online.txt`` is left to the caller (it writes the whole sequence's at the end)."""
        self.cfg = cfg
        self.seq = seq
        self.viewer = viewer
        self.progress = progress
        cam = seq.camera
        odo = seq.odometry
        pipelined = cfg.run_mode is RunMode.PIPELINED
        # Pipelined: the worker process builds and runs the back end; this process has none.
        self.vo = Odometry(cam, cfg, use_wheels=odo is not None,
                           static_mask=load_static_mask(cfg.frontend.mask, (cam.height, cam.width)),
                           wheel_comment=odo.comment if odo is not None else "", remote_backend=pipelined)
        self.use_odometry = self.vo.use_odometry
        self.frontend = self.vo.frontend
        self.n_skipped = 0
        self.provider = DataProvider(seq, cfg.checks, cfg.max_frames, cfg.frontend.mask_folder,
                                     prefetch=PREFETCH_FRAMES if pipelined else 0)
        self._wheel_next = 0  # next sample of seq.odometry to feed
        self.records: list[FrameRecord] = []
        # Pipelined: the back end runs in a worker process; frames wait here (in order) for their keyframe.
        self.worker: BackendWorker | None = None
        if pipelined:
            self.worker = worker if worker is not None else BackendWorker()
            self.worker.start(cam, cfg.backend, self.use_odometry, cfg.opencv_threads)
        self._pending: deque[tuple[TrackedFrame, Frame | None]] = deque()
        self._give_up: Callable[[], bool] = lambda: False  # stop waiting for the worker (a signal while draining)
        self._journal = TumJournal(cfg.output / "trajectory_online.txt", ONLINE_HEADER + " (run in progress)") \
            if journal and continuation is None else None
        self._run_journal = RunJournal(cfg.output / JOURNAL_NAME, {
            "pid": os.getpid(), "started": time.time(), "run_mode": cfg.run_mode.value, "sequence": str(cfg.sequence),
            "use_odometry": self.use_odometry, "use_ground": self.vo.plan.use_ground,
            **({} if continuation is None else {"seam_frame": int(continuation)})},
            first_frame=seq.first_frame if continuation is not None else None) if journal else None
        self._window: list[int] = []  # keyframes in the back end's window after the latest result
        self._kf_time: dict[int, float] = {}
        self._last_kf_t: float | None = None  # the newest finished keyframe's time

    # The per-frame state lives in the streaming object; these views keep the pipeline's names.
    @property
    def frames(self) -> list[tuple[int, float]]:
        return self.vo.frames

    @property
    def kf_frames(self) -> list[int]:
        return self.vo.kf_frames

    @property
    def online(self) -> list[np.ndarray]:
        return self.vo.online

    @property
    def notes(self) -> list[str]:
        return self.vo.notes

    def assemble_trajectory(self) -> Trajectory:
        return self.vo.smoothed_trajectory()

    def _feed_wheels(self, t: float) -> None:
        """Give the streaming object the wheel samples up to time t and the first one after it, as a robot's
        loop has them when it handles a frame (wheels report at 50-100 Hz, faster than a frame is processed):
        the wheel pose at the frame's time is then interpolated, not extrapolated."""
        odo = self.seq.odometry
        if odo is None:
            return
        end = min(int(np.searchsorted(odo.timestamps, t, side="left")) + 1, len(odo.timestamps))
        for i in range(self._wheel_next, end):
            self.vo.add_wheel_odometry(float(odo.timestamps[i]), float(odo.x[i]), float(odo.y[i]), float(odo.yaw[i]))
        self._wheel_next = max(self._wheel_next, end)

    # ------------------------------------------------------------------ main loop
    def run(self) -> RunResult:
        """Process every frame. Ctrl-C and SIGTERM stop the run between two frames, so the outputs always describe
        whole frames (a second Ctrl-C aborts the frame in progress); the back end's keyframes in flight are then
        still waited for, unless one more signal comes (``runtime/stop.py``)."""
        t_start = time.perf_counter()
        interrupted = False
        with stop.guarded(stop.Phase.DEFER), opencv_threads(self.cfg.opencv_threads):
            try:
                self._loop()
            except stop.Interrupted:
                interrupted = True
            finally:
                if self.worker is not None:
                    self.worker.close()
            interrupted = interrupted or stop.requested() is not None
        if interrupted:
            last = self.frames[-1][0] if self.frames else -1
            log.warning("interrupted after frame %d: writing the results so far", last)
        return self.result(time.perf_counter() - t_start, interrupted)

    def _loop(self) -> None:
        """Every frame through the front end (and the back end, or the worker), then the back end drained."""
        n_total = len(self.provider)
        with stop.abortable():
            for n_read, item in enumerate(self.provider, 1):
                self._step(item, n_read == n_total)
                if self.progress is not None:  # frames through the front end (pipelined: some still wait)
                    self.progress(n_read, len(self.kf_frames))
                if stop.requested() is not None:
                    break
        n_signals = stop.count()
        self._give_up = lambda: stop.count() > n_signals  # one more signal: stop waiting for the back end
        if self.worker is not None and self.seq.groundtruth is not None:
            load_in_background("windowvo.eval.metrics")  # the evaluation's evo and scipy, while we wait
        self._drain(block=True)  # keyframes still with the back-end process
        if self.worker is not None:
            report = self.worker.finish(give_up=self._give_up)
            self.vo.remote_report = report if report is not None else ScaleReport.lost(self.use_odometry)

    def result(self, wall_s: float = 0.0, interrupted: bool = True) -> RunResult:
        """What the run has computed so far (all of it after :meth:`run`); closes the online journal."""
        traj = self.vo.smoothed_trajectory()
        self.close()
        return RunResult(
            n_frames=len(self.frames),
            n_keyframes=len(self.kf_frames),
            n_skipped=self.n_skipped,
            wall_s=wall_s,
            trajectory=traj,
            records=self.records,
            monocular=not self.use_odometry,
            scale=self.vo.scale_report(),
            interrupted=interrupted,
            frontend_ms=[r.frontend_ms for r in self.records if r.frontend_ms > 0],
            backend_ms=[r.backend_ms for r in self.records if r.is_keyframe],
            notes=self.notes,
            last_frame_index=self.frames[-1][0] if self.frames else -1,
            trajectory_online=self.vo.online_trajectory(),
            wheel_time_offset=self.vo.wheel_time_offset(),
        )

    def _step(self, item, is_last: bool) -> None:
        """Track one frame; in pipelined mode its keyframe goes to the back-end process and the frame waits
        (in order) for that result, sequentially it is finished at once."""
        self._feed_wheels(item.timestamp)
        if isinstance(item, SkippedFrame):
            log.warning("skipping %s", item.reason)
            tracked = self.vo.track_skipped(item.index, item.timestamp, item.reason)
            frame = None
        else:
            tracked = self.vo.track(item.timestamp, item.image, index=item.index, mask=item.mask, is_last=is_last)
            frame = item
        if self.worker is None:
            self._finish(tracked, frame, self.vo.run_backend(tracked))
            return
        if tracked.is_keyframe:
            assert tracked.frontend is not None
            self.worker.submit(tracked.frontend, tracked.odom)
        self._pending.append((tracked, frame))
        self._drain(block=self.worker.in_flight > MAX_IN_FLIGHT)

    def _drain(self, block: bool) -> None:
        """Finish the waiting frames, in order, as far as the back-end results allow (all of them when
        ``block``; a non-keyframe only needs the keyframes before it)."""
        while self._pending:
            tracked, frame = self._pending[0]
            bo = None
            if tracked.is_keyframe:
                assert self.worker is not None
                bo = self.worker.result(block=block, give_up=self._give_up)
                if bo is None:
                    return
            self._pending.popleft()
            self._finish(tracked, frame, bo)

    def _finish(self, tracked: TrackedFrame, frame: Frame | None, bo: BackendOutput | None) -> None:
        est = self.vo.resolve(tracked, bo)
        if est.frontend is None:
            self.n_skipped += int(est.skipped)
            self.records.append(skipped_record(est))
        else:
            # The frame counts as processed only once everything about it is known (an interrupt
            # in the middle leaves frames and records in step).
            self.records.append(self._record(est.frontend, est.backend, est.note, est.latency_ms))
        if self.viewer is not None:
            self.viewer.log_frame(frame, est)
        self._journal_frame(est, bo)

    def _journal_frame(self, est: FrameEstimate, bo: BackendOutput | None) -> None:
        """The frame's lines in the journals; at a keyframe, the keyframes that left the window (final) too, and a
        flush: a kill loses at most the frames since the last finished keyframe."""
        if self._journal is not None:
            self._journal.add(est.timestamp, est.T_world_base)
        if self._run_journal is not None:
            odo = self.vo.wheels_on_camera_clock()  # as the finished run's interpolation reads them
            wheel_m = None
            if odo is not None and self._last_kf_t is not None and est.timestamp > self._last_kf_t:
                wheel_m = odo.distance(self._last_kf_t, est.timestamp)
            self._run_journal.frame(self.records[-1], est.T_world_base, wheel_m)
        if bo is not None:
            self._kf_time[est.frame_index] = est.timestamp
            final = [k for k in self._window if k not in bo.keyframe_poses] + list(bo.earlier_keyframe_poses)
            if self._run_journal is not None:
                for k in dict.fromkeys(final):
                    if k in self._kf_time and k in self.vo.kf_pose_by_frame:
                        self._run_journal.keyframe(k, self._kf_time[k], self.vo.kf_pose_by_frame[k])
            self._window = list(bo.keyframe_poses)
        if est.is_keyframe:
            self._last_kf_t = est.timestamp
            for j in (self._journal, self._run_journal):
                if j is not None:
                    j.flush()

    def close(self) -> None:
        """Close the online journal (``trajectory_online.txt``) and flush the run journal; the final outputs are
        written by the caller, which then closes the run journal (:meth:`end_journal`)."""
        if self._journal is not None:
            self._journal.close()
            self._journal = None
        if self._run_journal is not None:
            self._run_journal.flush()

    def end_journal(self, end: str | None) -> None:
        """Close the run journal, marking how the run ended once its outputs are written (None: it failed)."""
        if self._run_journal is not None:
            self._run_journal.close(end)
            self._run_journal = None

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
            base_rocking_deg=round(bo.base_rocking_deg, 4) if bo is not None else float("nan"),
            level_frame=bo.level_frame if bo is not None else False,
            floor_tilt_x_deg=round(bo.floor_tilt_x_deg, 4) if bo is not None else float("nan"),
            floor_tilt_y_deg=round(bo.floor_tilt_y_deg, 4) if bo is not None else float("nan"),
            floor_tilt_se_deg=round(bo.floor_tilt_se_deg, 4) if bo is not None else float("nan"),
            floor_normal_learnt=bo.floor_normal_learnt if bo is not None else False,
            cue_disagreement=round(bo.cue_disagreement, 5) if bo is not None else float("nan"),
            cues_agree=bo.cues_agree if bo is not None else None,
            wheel_yaw_scale=round(bo.wheel_yaw_scale, 6) if bo is not None else float("nan"),
            road_step_ratio=round(bo.road_step_ratio, 5) if bo is not None else float("nan"),
            road_pitch_deg=round(bo.road_pitch_deg, 4) if bo is not None else float("nan"),
            wheel_step_sigmas=round(bo.wheel_step_sigmas, 3) if bo is not None else float("nan"),
            wheel_slip=bo.wheel_slip if bo is not None else None,
        )


def skipped_record(est: FrameEstimate) -> FrameRecord:
    """The stats row of a frame that never reached the front end (black, duplicate, unreadable)."""
    return FrameRecord(frame_index=est.frame_index, timestamp=est.timestamp, n_tracked=0, n_inliers=0, n_detected=0,
                       parallax_px=0.0, rot_comp_parallax_px=0.0, inlier_ratio=0.0, cheirality_ratio=0.0, spread=0.0,
                       is_keyframe=False, keyframe_reason="", gate="", backend_status="", n_landmarks=0,
                       reprojection_rms_px=float("nan"), frontend_ms=0.0, backend_ms=0.0, note=est.note)
