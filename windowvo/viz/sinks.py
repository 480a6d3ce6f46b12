"""Where a Rerun recording goes, opened so that nothing waits without bound.

Every sink is checked before the recording is attached to it: a viewer to connect to must answer on its
port, a viewer to spawn needs a display and must start listening in time (else it is killed and reaped),
a server to serve needs its port free, and a file to save needs room on its disk. A live sink that fails
falls back to saving OUTPUT/recording.rrd; the caller logs the one warning line that says what happened.
"""

from __future__ import annotations

import contextlib
import enum
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ..config import connect_url_problem
from ..errors import ConfigError

CONNECT_PROBE_S = 3.0  # a viewer to connect to must accept a TCP connection within this
SPAWN_WAIT_S = 15.0  # a spawned viewer must listen on its port within this (else killed)
SPAWN_GRACE_S = 2.0  # ... and must still run this long after it listens (it opens its window then)
SPAWN_PORT = 9876  # rerun's default viewer port
FLUSH_TIMEOUT_S = 5.0  # the recording's final flush waits at most this
CLOSE_TIMEOUT_S = 7.0  # closing the sinks waits at most this (gRPC waits up to 5 s for a last try)
DISK_RESERVE_BYTES = 64 * 2**20  # a saved recording stops when its disk has less room left than this


class SinkKind(str, enum.Enum):
    """Where the recording actually goes (after any fallback)."""

    NONE = "none"
    FILE = "file"
    VIEWER = "viewer"  # a native viewer, spawned or connected to
    SERVER = "server"  # the web viewer served by this process


class SinkFailed(Exception):
    """A sink could not be opened; the message says why, in words for the one warning line."""


@dataclass(frozen=True)
class ConnectTarget:
    url: str
    host: str
    port: int


def parse_connect_url(url: str) -> ConnectTarget:
    """``viz.connect_url`` checked as rerun wants it (``config.connect_url_problem``), with its host and port."""
    problem = connect_url_problem(url)
    if problem is not None:
        raise ConfigError(f"viz.connect_url {problem}")
    parts = urlsplit(url)
    port = parts.port
    if port is None:
        port = 443 if parts.scheme == "rerun+https" else SPAWN_PORT
    assert parts.hostname is not None
    return ConnectTarget(url, parts.hostname, port)


def bounded(fn: Callable[[], Any], timeout_s: float, name: str) -> tuple[bool, BaseException | None]:
    """Run ``fn`` in a daemon thread and wait at most ``timeout_s``: (finished, the exception it raised)."""
    box: list[BaseException] = []

    def target() -> None:
        try:
            fn()
        except BaseException as err:  # handed back to the caller
            box.append(err)

    th = threading.Thread(target=target, name=name, daemon=True)
    th.start()
    th.join(timeout_s)
    return not th.is_alive(), (box[0] if box else None)


def port_answers(host: str, port: int, timeout_s: float = CONNECT_PROBE_S) -> str | None:
    """None when something accepts TCP connections at host:port within the time, else why not."""
    result: list[str | None] = []

    def probe() -> None:
        try:
            with socket.create_connection((host, port), timeout=timeout_s):
                result.append(None)
        except OSError as err:
            result.append(err.strerror or type(err).__name__)

    done, _ = bounded(probe, timeout_s + 1.0, "windowvo-probe")
    if not done or not result:
        return f"no answer within {timeout_s:.0f} s"
    return result[0]


def port_free(port: int) -> bool:
    """Whether this process could listen on ``port`` (all interfaces)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def has_display() -> bool:
    """Whether a native window can open: always on macOS and Windows, else DISPLAY or WAYLAND_DISPLAY set."""
    if sys.platform == "darwin" or os.name == "nt":
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or os.environ.get("WAYLAND_SOCKET"))


def _last_line(fh: Any) -> str:
    with contextlib.suppress(OSError, ValueError):
        fh.seek(0)
        lines = [ln.strip() for ln in fh.read().decode("utf-8", "replace").splitlines() if ln.strip()]
        for ln in reversed(lines):
            if "rror" in ln:  # Error: / ERROR
                return re.sub(r" at \S+\.rs:\d+:", ":", ln)[-200:]  # without the Rust source location
        return lines[-1][-200:] if lines else ""
    return ""


def reap(proc: subprocess.Popen) -> None:
    """Kill a spawned viewer (its whole process group) and wait for it, so that no zombie is left."""
    if proc.poll() is None:
        with contextlib.suppress(OSError):
            if hasattr(os, "killpg"):
                os.killpg(proc.pid, 9)
            else:  # pragma: no cover - Windows
                proc.kill()
    with contextlib.suppress(subprocess.TimeoutExpired, OSError):
        proc.wait(timeout=5.0)


def spawn_viewer(port: int = SPAWN_PORT, wait_s: float = SPAWN_WAIT_S) -> subprocess.Popen | None:
    """Start rerun's native viewer listening on ``port`` and wait until it listens.

    Returns None when a viewer (or anything) already listens there: the recording goes to it. Raises
    :class:`SinkFailed` when there is no display, or the viewer exits or does not listen in time (it is
    then killed and reaped). A viewer that started is left running, in a session of its own."""
    if not has_display():
        raise SinkFailed("no display (neither DISPLAY nor WAYLAND_DISPLAY is set) to open a viewer window")
    if port_answers("127.0.0.1", port, 0.5) is None:
        return None
    cmd = [sys.executable, "-m", "rerun", "--port", str(port), "--memory-limit", "75%", "--expect-data-soon"]
    with tempfile.TemporaryFile() as err:  # the viewer's own messages: the reason it failed, if it does
        try:
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=err, stderr=err, start_new_session=True)
        except OSError as e:
            raise SinkFailed(f"the viewer could not be started ({e})") from None
        try:
            _await_listening(proc, err, port, wait_s)
        except SinkFailed:
            reap(proc)
            raise
    return proc


def _await_listening(proc: subprocess.Popen, err: Any, port: int, wait_s: float) -> None:
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            reason = _last_line(err)
            raise SinkFailed(f"the viewer exited at start (code {proc.returncode})" + (f": {reason}" if reason else ""))
        if port_answers("127.0.0.1", port, 0.5) is None:
            break
        time.sleep(0.1)
    else:
        raise SinkFailed(f"the viewer did not listen on port {port} within {wait_s:.0f} s")
    # The viewer listens before it opens its window: one that cannot open it exits right after.
    try:
        code = proc.wait(timeout=SPAWN_GRACE_S)
    except subprocess.TimeoutExpired:
        return
    reason = _last_line(err)
    raise SinkFailed(f"the viewer exited at start (code {code})" + (f": {reason}" if reason else ""))


def disk_room(path: Path) -> int:
    """Bytes free for this process on the disk that holds ``path`` (or its nearest existing parent)."""
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return int(shutil.disk_usage(p).free)
    except OSError:
        return 0


def check_disk(path: Path, reserve: int | None = None) -> None:
    """Raise :class:`SinkFailed` when the disk of ``path`` has less room than the reserve
    (``DISK_RESERVE_BYTES`` unless given)."""
    reserve = DISK_RESERVE_BYTES if reserve is None else reserve
    room = disk_room(path)
    if room < reserve:
        raise SinkFailed(f"the disk of {path.parent} has {room / 2**20:.1f} MiB left (under the "
                         f"{reserve / 2**20:.0f} MiB kept free for the run's other outputs)")


def remove_partial(path: Path | None) -> None:
    """Delete a recording file that was dropped (only a regular file: never a device like /dev/full)."""
    if path is not None and path.is_file() and not path.is_symlink():
        with contextlib.suppress(OSError):
            path.unlink()
