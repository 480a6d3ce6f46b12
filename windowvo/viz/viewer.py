"""Open a saved run's recording in rerun's viewer: a native window, or the web viewer served from here.

The command line (``python -m windowvo.view``) is a thin wrapper over :func:`open_recording`.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

from ..errors import WindowVOError
from .sinks import has_display

WEB_HINT = "use --web to serve the web viewer and open it in a browser"
STOP_WAIT_S = 5.0  # after Ctrl-C, the viewer gets this long to stop before it is killed


class ViewerError(WindowVOError):
    """The recording cannot be shown: none at the path, no display for a window, or the viewer failed."""


def find_recording(path: Path) -> Path:
    """The .rrd file of ``path``: the file itself, or ``recording.rrd`` in a run's output folder."""
    rrd = path / "recording.rrd" if path.is_dir() else path
    if not rrd.is_file():
        raise ViewerError(f"no recording at {rrd} (run with viz.rerun=save)")
    return rrd


def viewer_command(rrd: Path, web: bool) -> list[str]:
    cmd = [sys.executable, "-m", "rerun", str(rrd)]
    if web:
        cmd.insert(3, "--web-viewer")
    return cmd


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (Linux: ``/proc/<pid>/task/<tid>/children``; elsewhere none are found)."""
    found: list[int] = []
    todo = [pid]
    while todo:
        parent = todo.pop()
        for children in Path(f"/proc/{parent}/task").glob("*/children"):
            with contextlib.suppress(OSError, ValueError):
                kids = [int(c) for c in children.read_text().split()]
                found += kids
                todo += kids
    return found


def _stop(proc: subprocess.Popen, started: list[int]) -> None:
    """Let the viewer stop on the Ctrl-C (passed on to it, in case only this process got one); after at most
    ``STOP_WAIT_S`` kill what is left of it and of the processes it started (``started``, as last seen, and any
    below it now: rerun's launcher starts the viewer binary, and a launcher gone alone can leave the binary
    serving, and holding our output open), and reap it."""
    below = list(dict.fromkeys([*started, *_descendants(proc.pid)]))
    with contextlib.suppress(ProcessLookupError):
        proc.send_signal(signal.SIGINT)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=STOP_WAIT_S)
    for pid in [*below, proc.pid]:
        if pid != proc.pid or proc.poll() is None:  # never signal the launcher's pid once it is reaped
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=STOP_WAIT_S)


def _wait(proc: subprocess.Popen, started: list[int]) -> int:
    """The viewer's exit code; meanwhile ``started`` holds the processes it started, as last seen."""
    while True:
        try:
            return proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            started[:] = _descendants(proc.pid) or started


def open_recording(path: Path, web: bool = False) -> int:
    """Show the recording of ``path`` until the viewer is closed (or Ctrl-C); returns the exit code
    (130 after Ctrl-C). Raises :class:`ViewerError` when there is nothing to show or no display for a
    native window."""
    rrd = find_recording(path)
    if not web and not has_display():
        raise ViewerError(f"no display to open the viewer window (neither DISPLAY nor WAYLAND_DISPLAY is set): "
                          f"{WEB_HINT}")
    try:
        proc = subprocess.Popen(viewer_command(rrd, web))  # in our process group: a terminal's Ctrl-C reaches it
    except OSError as err:
        raise ViewerError(f"cannot start rerun's viewer ({err})") from None
    started: list[int] = []
    try:
        code = _wait(proc, started)
    except KeyboardInterrupt:
        _stop(proc, started)
        return 128 + signal.SIGINT
    if code != 0 and not web:
        raise ViewerError(f"the viewer exited with code {code} (see its message above); on a machine without "
                          f"a screen, {WEB_HINT}")
    return code
