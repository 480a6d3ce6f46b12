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


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    """Send ``sig`` to the viewer's process group (rerun's launcher and the viewer binary it starts)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, sig)


def _stop(proc: subprocess.Popen) -> None:
    """Pass the Ctrl-C on to the viewer's process group; kill the group if it has not stopped in
    ``STOP_WAIT_S``, and reap it. The whole group: killing the launcher alone can leave the viewer binary
    serving, and holding our output open."""
    _signal_group(proc, signal.SIGINT)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=STOP_WAIT_S)
    _signal_group(proc, signal.SIGKILL)  # whatever of the group is left (the launcher may be gone already)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=STOP_WAIT_S)


def open_recording(path: Path, web: bool = False) -> int:
    """Show the recording of ``path`` until the viewer is closed (or Ctrl-C); returns the exit code
    (130 after Ctrl-C). Raises :class:`ViewerError` when there is nothing to show or no display for a
    native window."""
    rrd = find_recording(path)
    if not web and not has_display():
        raise ViewerError(f"no display to open the viewer window (neither DISPLAY nor WAYLAND_DISPLAY is set): "
                          f"{WEB_HINT}")
    try:
        # A process group of its own, so that a stop reaches every process of the viewer (see _stop).
        proc = subprocess.Popen(viewer_command(rrd, web), start_new_session=True)
    except OSError as err:
        raise ViewerError(f"cannot start rerun's viewer ({err})") from None
    try:
        code = proc.wait()
    except KeyboardInterrupt:
        _stop(proc)
        return 128 + signal.SIGINT
    if code != 0 and not web:
        raise ViewerError(f"the viewer exited with code {code} (see its message above); on a machine without "
                          f"a screen, {WEB_HINT}")
    return code
