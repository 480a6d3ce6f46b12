"""Ctrl-C and SIGTERM from the first line of a run to the last.

The command line installs :func:`install` before anything heavy is imported. A signal is then always
recorded (:func:`requested`); whether it also raises :class:`Interrupted` depends on the phase:

- ``RAISE`` (loading, before any frame is computed): there is nothing to save, so the signal unwinds at once
  and the command line exits 130 (SIGINT) or 143 (SIGTERM) with one line;
- ``DEFER`` (before the command line is set up, the frame loop, the back end draining, writing the outputs): the
  signal is only recorded; the frame loop stops between two frames and every output is still written. A second
  Ctrl-C during the frame loop (``abortable``) aborts the frame in progress.

A worker process whose one call makes many runs (``tools/executors.py``: a scale-suite case is eight) keeps the
handlers for the whole call (:func:`between_runs`): outside a run a signal unwinds at once, and a signal a run
recorded raises once that run has written its outputs, so no later run of the call starts.

Light on imports on purpose: ``python -m windowvo.run`` installs it before OpenCV and GTSAM are loaded.
"""

from __future__ import annotations

import contextlib
import enum
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Phase(enum.Enum):
    RAISE = "raise"  # a signal unwinds now (nothing computed yet)
    DEFER = "defer"  # a signal is recorded; the run stops at the next safe point


class Interrupted(BaseException):
    """A stop signal unwound a phase that had nothing to save. Not an ``Exception``: no handler swallows it."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@dataclass
class StopState:
    signum: int | None = None  # the first stop signal received
    count: int = 0  # stop signals received
    phase: Phase = Phase.DEFER
    abortable: bool = False  # a second SIGINT aborts (the frame loop)
    installed: bool = False
    previous: dict[int, object] = field(default_factory=dict)
    depth: int = 0  # guarded blocks open
    # The phase outside every guarded block when the handlers outlive the runs (``between_runs``: a worker process
    # whose call makes many runs); None: the phase the last block left
    between: Phase | None = None


STATE = StopState()


def _on_signal(signum: int, frame: object) -> None:
    first = STATE.signum is None
    STATE.count += 1
    if first:
        STATE.signum = signum
    if STATE.phase is Phase.RAISE or (not first and signum == signal.SIGINT and STATE.abortable):
        raise Interrupted(signum)


def install() -> bool:
    """Handle SIGINT and SIGTERM (main thread only; elsewhere a no-op). True if this call installed them."""
    if STATE.installed or threading.current_thread() is not threading.main_thread():
        return False
    for sig in STOP_SIGNALS:
        STATE.previous[sig] = signal.signal(sig, _on_signal)
    STATE.installed = True
    return True


def uninstall() -> None:
    """Put back the handlers :func:`install` replaced and forget any signal received."""
    if not STATE.installed:
        return
    for sig, handler in STATE.previous.items():
        signal.signal(sig, handler)  # type: ignore[arg-type]
    STATE.previous.clear()
    STATE.installed = False
    STATE.between = None
    STATE.signum = None
    STATE.count = 0
    STATE.phase = Phase.DEFER
    STATE.abortable = False


def requested() -> int | None:
    """The stop signal received so far (None: none)."""
    return STATE.signum


def check() -> None:
    """Raise :class:`Interrupted` now if a stop signal came while it was deferred (between phases)."""
    if STATE.signum is not None:
        raise Interrupted(STATE.signum)


def set_phase(phase: Phase) -> None:
    """Enter a phase; entering ``RAISE`` with a signal already recorded raises at once."""
    STATE.phase = phase
    if phase is Phase.RAISE:
        check()


@contextlib.contextmanager
def guarded(phase: Phase) -> Iterator[None]:
    """Handlers installed for the block (unless already installed, e.g. by the command line), in ``phase``;
    what this installed is removed afterwards. The phase is left as the block left it: once frames are computed
    (``DEFER``), no later step of the run unwinds on a signal; except in a worker (``between_runs``), where leaving
    the outermost block puts its phase back and, with ``RAISE``, a signal the run recorded then raises."""
    mine = install()
    STATE.depth += 1
    try:
        set_phase(phase)
        yield
    except BaseException:
        _leave(mine)
        raise
    _leave(mine)
    if STATE.depth == 0 and STATE.between is Phase.RAISE:
        check()  # a signal the run recorded: its outputs are written, and nothing after it runs


def _leave(mine: bool) -> None:
    STATE.depth -= 1
    if mine:
        uninstall()
    elif STATE.depth == 0 and STATE.between is not None:
        STATE.phase = STATE.between


def between_runs(phase: Phase) -> None:
    """Handlers installed for the rest of the process, and ``phase`` outside every guarded block (a run's): a
    worker whose call makes many runs (``tools/executors.py``) with ``RAISE`` ends the call at a signal, once the run
    in progress has written its outputs, or at once between runs."""
    install()
    STATE.between = phase
    set_phase(phase)


@contextlib.contextmanager
def abortable() -> Iterator[None]:
    """A second Ctrl-C aborts the block (the frame loop)."""
    STATE.abortable = True
    try:
        yield
    finally:
        STATE.abortable = False


def count() -> int:
    """How many stop signals came so far (a new one during a wait means: stop waiting)."""
    return STATE.count


def exit_code(signum: int) -> int:
    """The shell's convention: 128 + the signal number (130 for SIGINT, 143 for SIGTERM)."""
    return 128 + int(signum)
