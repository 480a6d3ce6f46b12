"""The back end in a worker process, so a run uses both cores (``run_mode: pipelined``).

Why a process and not a thread: GTSAM's Python bindings hold the GIL for the whole of
``ISAM2.update`` (two iSAM2 workloads in two threads ran at 0.88x of sequential; iSAM2 beside
KLT in a thread, 1.13x), so a back-end thread cannot overlap with decoding and the front end.

The main process decodes frames and runs the front end; each keyframe's typed, picklable
payload (``FrontendOutput``, ``OdometryStep``) goes to the worker, which owns the
``SlidingWindowBackend`` and sends ``BackendOutput`` back, in order. The back end sees exactly
the inputs of the sequential mode, in the same order, so the trajectories are the same bit for bit.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Callable

from ..backend.report import ScaleReport
from ..camera import CameraModel
from ..config import BackendConfig
from ..errors import WindowVOError
from ..types import BackendOutput, FrontendOutput, OdometryStep

log = logging.getLogger(__name__)

# Keyframes in flight before the main process waits for the worker: enough to keep both cores busy,
# few enough that the causal poses come out with a short delay and memory stays bounded.
MAX_IN_FLIGHT = 16
# How often (s) a blocked wait checks that the worker is still alive.
POLL_S = 1.0
_NOTHING = object()  # no message within POLL_S
STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


class Reply(str, enum.Enum):
    """What the worker sends back with each message."""

    OK = "ok"  # a keyframe's BackendOutput
    ERROR = "error"  # the back end failed (the message text); the worker ends
    DONE = "done"  # the final ScaleReport (or None: no keyframe came); the worker ends


def _exit_when_orphaned(parent_pid: int) -> None:
    """The worker's watch: end this process as soon as the main process is gone. The loop below checks that too,
    but only between messages: a main process killed (SIGKILL) while its feeder thread was writing a keyframe's
    message (an image is several pipe buffers) leaves the worker blocked for ever reading the rest, since the
    worker holds a copy of the inbox's write end and so never sees the end of the pipe; it would hold the run's
    stdout and stderr open with it (measured: a parent waiting for them hung)."""
    while os.getppid() == parent_pid:
        time.sleep(POLL_S)
    os._exit(0)


def _serve(inbox, outbox, parent_pid: int) -> None:
    """Worker loop: the first message sets up one back end (camera, config, wheels), then keyframes until
    ``None`` arrives; then its final report. It also ends when the main process is gone (killed with
    SIGKILL, say), checked before every message, so no orphan is left behind."""
    # Ctrl-C and SIGTERM go to the whole process group: the main process decides when to stop. They were blocked
    # from before this process started (BackendWorker), so none came through while Python was starting.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    threading.Thread(target=_exit_when_orphaned, args=(parent_pid,), name="windowvo-orphan-watch", daemon=True).start()
    from ..backend.smoother import SlidingWindowBackend

    be = None
    while True:
        try:
            msg = inbox.get(timeout=POLL_S)
        except queue.Empty:
            msg = _NOTHING
        if os.getppid() != parent_pid:
            # Nobody will read the results still buffered for the outbox's pipe: without this, exiting
            # waits for its feeder thread, which blocks on the full pipe for ever (an orphan).
            outbox.cancel_join_thread()
            return
        if msg is _NOTHING:
            continue
        if msg is None:
            outbox.put((Reply.DONE, be.scale_report() if be is not None else None))
            return
        if be is None:
            camera, cfg, use_odometry, n_threads = msg
            if n_threads > 0:  # the process is the back end's alone: nothing to put back
                import cv2

                cv2.setNumThreads(n_threads)
            be = SlidingWindowBackend(camera, cfg, use_odometry)
            continue
        fo, odom = msg
        try:
            outbox.put((Reply.OK, be.add_keyframe(fo, odom)))
        except WindowVOError as err:
            outbox.put((Reply.ERROR, str(err)))
            return


class BackendWorker:
    """A back end running in its own process: ``start`` it, ``submit`` keyframes, ``result`` their outputs
    in order. The process is spawned at construction, so its imports overlap with loading the sequence."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")  # no fork of a process holding OpenCV and GTSAM threads
        self._inbox = ctx.Queue()
        self._outbox = ctx.Queue()
        self._proc = ctx.Process(target=_serve, args=(self._inbox, self._outbox, os.getpid()),
                                 name="windowvo-backend", daemon=True)
        # The child inherits the signal mask: a Ctrl-C to the process group while it imports is held, then ignored.
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
        try:
            self._proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        self.in_flight = 0
        self.report: ScaleReport | None = None
        self._ready: deque[BackendOutput] = deque()

    def start(self, camera: CameraModel, cfg: BackendConfig, use_odometry: bool, opencv_threads: int = 0) -> None:
        """Build the worker's back end; ``opencv_threads`` (the config's key; 0: OpenCV's default) for its process."""
        self._inbox.put((camera, cfg, use_odometry, opencv_threads))

    def submit(self, fo: FrontendOutput, odom: OdometryStep | None) -> None:
        self._inbox.put((fo, odom))
        self.in_flight += 1

    def _receive(self, block: bool, give_up: Callable[[], bool] | None = None) -> tuple[Reply, object] | None:
        """The worker's next message; None if there is none and not ``block``, or ``give_up()`` says stop waiting
        (checked every POLL_S)."""
        while True:
            try:
                return self._outbox.get(block=block, timeout=POLL_S if block else None)
            except queue.Empty:
                if not block or (give_up is not None and give_up()):
                    return None
                if not self._proc.is_alive():
                    raise WindowVOError(
                        f"the back-end process died (exit code {self._proc.exitcode}); a script that runs windowvo "
                        "with run_mode=pipelined needs Python's `if __name__ == '__main__':` guard, or use "
                        "run_mode=sequential") from None

    def result(self, block: bool, give_up: Callable[[], bool] | None = None) -> BackendOutput | None:
        """The next keyframe's output, or None if it is not ready and ``block`` is False (or ``give_up()``)."""
        if not self._ready:
            msg = self._receive(block, give_up)
            if msg is None:
                return None
            kind, payload = msg
            if kind is Reply.ERROR:
                raise WindowVOError(str(payload))
            assert kind is Reply.OK and isinstance(payload, BackendOutput)
            self._ready.append(payload)
        self.in_flight -= 1
        return self._ready.popleft()

    def finish(self, give_up: Callable[[], bool] | None = None) -> ScaleReport | None:
        """Wait for the worker to end; returns its scale report (None: it never had a keyframe, or ``give_up()``
        said stop waiting)."""
        self._inbox.put(None)
        while True:
            msg = self._receive(block=True, give_up=give_up)
            if msg is None:
                return None
            kind, payload = msg
            if kind is Reply.DONE:
                assert payload is None or isinstance(payload, ScaleReport)
                self.report = payload
                break
            if kind is Reply.ERROR:
                raise WindowVOError(str(payload))
        self._proc.join(timeout=10)
        return self.report

    @property
    def pid(self) -> int | None:
        """The worker process's id."""
        return self._proc.pid

    @property
    def alive(self) -> bool:
        """The worker process is running."""
        return self._proc.is_alive()

    def close(self) -> None:
        """Stop the worker whatever state it is in (errors, interrupts). It ignores SIGTERM (the main
        process decides when to stop), so a worker that does not end by itself is killed."""
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=5)
        self._inbox.cancel_join_thread()
        self._inbox.close()
        self._outbox.close()


def stop_resource_tracker() -> None:
    """Stop multiprocessing's resource tracker (a helper process started with the worker) and wait for it: left
    alone it outlives the main process by a moment, a process left behind in the run's group. Call it at the very
    end, once no worker is in use (the queues' semaphores are collected first, so nothing starts it again)."""
    import gc
    from multiprocessing import resource_tracker

    gc.collect()
    stop_tracker = getattr(getattr(resource_tracker, "_resource_tracker", None), "_stop", None)
    if callable(stop_tracker):
        with contextlib.suppress(Exception):
            stop_tracker()
