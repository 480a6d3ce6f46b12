"""Per-stage CPU budget: the thread CPU time each stage of a run takes, per frame and per keyframe.

Off unless a :class:`StageRecorder` is started (``python -m windowvo.bench --suite stages`` does, around one
job). Off, every timing point is one module-global check (``section`` hands back a shared no-op context,
``Laps`` does nothing). On, the stages add their thread CPU time (``time.thread_time``) to the recorder: the
frame's stages in the thread that started it (the run's), a stage in any other thread (the recording's
logging thread) to that stage's list of its own. Timers only read clocks, so a run's results are the same
bit for bit with the recorder on or off.

A frame lasts from the start of its decoding to the start of the next frame's (or the end of the input):
everything the run's thread does for it (decoding, the front end, the back end at a keyframe, queueing it
for the recording, the journal) falls in it. The stages are exclusive (none is timed inside another), so a
frame's stages sum to at most its total; the rest is bookkeeping nobody times (journal, wheel buffer).
Before the first frame (loading, set-up) and after the last (outputs, closing the recording) are the run's.
Frames are delimited only where the run's thread decodes them (the sequential run mode); in the pipelined
mode the decoding thread and the back-end process time nothing, so the budget is the sequential mode's.
"""

from __future__ import annotations

import contextlib
import enum
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from types import TracebackType


class Stage(str, enum.Enum):
    """The timed stages of a run, in pipeline order."""

    DECODE = "decode"
    INPUT_CHECKS = "input checks (black, duplicate)"
    GAIN = "gain normalisation"
    TRACKING = "tracking (KLT / ORB matching)"
    DETECTION = "detection (new corners)"
    UNDISTORTION = "undistortion"
    RANSAC = "RANSAC (essential matrix)"
    KEYFRAME = "keyframe decision, pose recovery, gates"
    BACKEND_GUESS = "back end: initial guess (PnP)"
    BACKEND_FACTORS = "back end: building the update's factors"
    BACKEND_FLOOR = "back end: floor (mount, retie, cue check, untie)"
    BACKEND_ISAM2 = "back end: iSAM2 update"
    BACKEND_ESTIMATE = "back end: estimate, landmark bookkeeping, output"
    RECORDING = "recording (run's thread)"
    RECORDING_THREAD = "recording (its logging thread)"
    OUTPUTS = "outputs (files, summary)"


class Scope(str, enum.Enum):
    """How often a stage runs."""

    FRAME = "frame"
    KEYFRAME = "keyframe"
    RUN = "run"  # once, before the first frame or after the last


BACKEND_STAGES = (Stage.BACKEND_GUESS, Stage.BACKEND_FACTORS, Stage.BACKEND_FLOOR, Stage.BACKEND_ISAM2,
                  Stage.BACKEND_ESTIMATE)
STAGE_SCOPE: dict[Stage, Scope] = {s: Scope.KEYFRAME if s in BACKEND_STAGES else Scope.FRAME for s in Stage}
STAGE_SCOPE[Stage.OUTPUTS] = Scope.RUN


@dataclass
class FrameStages:
    """One frame's stage times (ms of the run's thread CPU) and its total."""

    index: int
    total_ms: float = 0.0
    ms: dict[Stage, float] = field(default_factory=dict)
    keyframe: bool = False

    @property
    def stages_ms(self) -> float:
        return float(sum(self.ms.values()))


@dataclass
class StageTimes:
    """What a recorder measured over one run (ms of thread CPU time)."""

    frames: list[FrameStages]
    before_frames_ms: float  # the run's thread before the first frame (loading, set-up)
    before_stages_ms: dict[Stage, float]  # the stages timed in it (the recording's set-up)
    after_frames_ms: float  # after the last frame (outputs, evaluation, closing the recording)
    after_stages_ms: dict[Stage, float]
    other_threads_ms: dict[Stage, list[float]]  # per call, in threads other than the run's

    @property
    def frames_ms(self) -> float:
        return float(sum(f.total_ms for f in self.frames))

    @property
    def total_ms(self) -> float:
        """The run's thread, first timing point to the end."""
        return self.before_frames_ms + self.frames_ms + self.after_frames_ms


class StageRecorder:
    """Collects the stage times of the thread that made it (the run's) and of other threads."""

    def __init__(self) -> None:
        self.thread = threading.get_ident()
        self._lock = threading.Lock()
        self._t_start = time.thread_time()
        self._t_frame = 0.0
        self._t_frames_end: float | None = None
        self._t_first: float | None = None
        self.frames: list[FrameStages] = []
        self.current: FrameStages | None = None
        self.before: dict[Stage, float] = {}
        self.after: dict[Stage, float] = {}
        self.other: dict[Stage, list[float]] = {}

    def add(self, stage: Stage, seconds: float) -> None:
        """``seconds`` of ``stage`` in the calling thread."""
        ms = 1000.0 * seconds
        if threading.get_ident() != self.thread:
            with self._lock:
                self.other.setdefault(stage, []).append(ms)
            return
        target = (self.current.ms if self.current is not None else
                  self.before if self._t_first is None else self.after)
        target[stage] = target.get(stage, 0.0) + ms

    def begin_frame(self, index: int) -> None:
        if threading.get_ident() != self.thread:
            return
        now = time.thread_time()
        self._close(now)
        if self._t_first is None:
            self._t_first = now
        self.current = FrameStages(index)
        self._t_frame = now

    def end_frames(self) -> None:
        """The input is done: the last frame ends here."""
        if threading.get_ident() == self.thread:
            self._close(time.thread_time())

    def mark_keyframe(self) -> None:
        if self.current is not None and threading.get_ident() == self.thread:
            self.current.keyframe = True

    def _close(self, now: float) -> None:
        if self.current is not None:
            self.current.total_ms = 1000.0 * (now - self._t_frame)
            self.frames.append(self.current)
            self.current = None
            self._t_frames_end = now

    def times(self) -> StageTimes:
        now = time.thread_time()
        self._close(now)
        first = self._t_first if self._t_first is not None else now
        frames_end = self._t_frames_end if self._t_frames_end is not None else first
        with self._lock:
            other = {k: list(v) for k, v in self.other.items()}
        return StageTimes(self.frames, 1000.0 * (first - self._t_start), dict(self.before),
                          1000.0 * (now - frames_end), dict(self.after), other)


_active: StageRecorder | None = None


@contextlib.contextmanager
def recording() -> Iterator[StageRecorder]:
    """Time the stages of whatever runs inside (one run at a time); read ``recorder.times()`` after."""
    global _active
    if _active is not None:
        raise RuntimeError("a stage recorder is already running")
    rec = _active = StageRecorder()
    try:
        yield rec
    finally:
        _active = None


class _Section:
    __slots__ = ("rec", "stage", "t0")

    def __init__(self, rec: StageRecorder, stage: Stage):
        self.rec, self.stage, self.t0 = rec, stage, 0.0

    def __enter__(self) -> None:
        self.t0 = time.thread_time()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.rec.add(self.stage, time.thread_time() - self.t0)


_OFF = contextlib.nullcontext()


def section(stage: Stage) -> contextlib.AbstractContextManager[None]:
    """``with section(Stage.X): ...`` adds the block's thread CPU time to X (a shared no-op when off)."""
    rec = _active
    return _OFF if rec is None else _Section(rec, stage)


class Laps:
    """Consecutive stages in one function: ``lap = Laps()`` starts the clock, ``lap(Stage.X)`` gives the time
    since the last lap (or the start) to X, ``lap.skip()`` drops it (time that belongs to no stage)."""

    __slots__ = ("rec", "t")

    def __init__(self) -> None:
        self.rec = _active
        self.t = time.thread_time() if self.rec is not None else 0.0

    def __call__(self, stage: Stage) -> None:
        if self.rec is not None:
            now = time.thread_time()
            self.rec.add(stage, now - self.t)
            self.t = now

    def skip(self) -> None:
        if self.rec is not None:
            self.t = time.thread_time()


def begin_frame(index: int) -> None:
    """Frame ``index`` starts (its decoding is next)."""
    if _active is not None:
        _active.begin_frame(index)


def end_frames() -> None:
    """No frame follows: the last one ends here."""
    if _active is not None:
        _active.end_frames()


def mark_keyframe() -> None:
    """The current frame is a keyframe (the back end runs on it)."""
    if _active is not None:
        _active.mark_keyframe()
