"""Opening the Rerun sink that ``viz.rerun`` names, with its checks and its fallback to saving.

:func:`open_sink` never raises for a sink that fails (it returns the warning to give), only
:class:`~windowvo.errors.ConfigError` for a malformed ``viz.connect_url``.
"""

from __future__ import annotations

import logging
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rerun as rr
import rerun.blueprint as rrb

from ..config import Config, RerunMode
from .sinks import (
    CLOSE_TIMEOUT_S,
    CONNECT_PROBE_S,
    SPAWN_PORT,
    ConnectTarget,
    SinkFailed,
    SinkKind,
    bounded,
    check_disk,
    parse_connect_url,
    port_answers,
    port_free,
    remove_partial,
    spawn_viewer,
)

log = logging.getLogger("windowvo.viz.rerun_logger")

WEB_PORT = 9090  # viz.rerun=serve: the web viewer's port (rerun's default)


@dataclass
class OpenedSink:
    """A recording stream and where it goes (after any fallback), with the one warning to give, if any."""

    rec: rr.RecordingStream
    kind: SinkKind = SinkKind.NONE
    path: Path | None = None  # the .rrd written, if the recording goes to a file
    viewer_process: subprocess.Popen | None = None  # a viewer spawned for it (left running)
    warning: str | None = None


def close_stream(rec: rr.RecordingStream, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
    """Close all of ``rec``'s sinks, waiting at most ``CLOSE_TIMEOUT_S``. When that is not enough (a viewer
    that accepted the connection but takes no data), rerun's exit hook is unregistered as well: it would
    otherwise wait for the same sink, without bound, when the process exits."""
    done, _err = bounded(rec.disconnect, timeout_s, "windowvo-rerun-close")
    if not done:
        rr.unregister_shutdown()
    return done


def open_sink(cfg: Config, bp: rrb.Blueprint, path: Path) -> OpenedSink:
    """Attach the recording to ``viz.rerun``'s sink; a live sink that fails falls back to saving ``path``."""
    s = OpenedSink(rr.RecordingStream("windowvo", make_default=False))
    mode = cfg.viz.rerun
    if mode is RerunMode.OFF:
        return s
    target = parse_connect_url(cfg.viz.connect_url) if mode is RerunMode.CONNECT else None
    try:
        if mode is RerunMode.SAVE:
            _save(s, path, bp)
        else:
            _open_live(s, mode, target, bp)
        return s
    except SinkFailed as err:
        failure = f"viz.rerun={mode.value}: {err}"
    if mode is RerunMode.SAVE:
        s.warning = f"{failure}; the run is not recorded"
        return s
    s.rec = rr.RecordingStream("windowvo", make_default=False)  # a fresh stream, whatever the failed one holds
    try:
        _save(s, path, bp)
    except SinkFailed as err:
        s.warning = f"{failure}; saving the recording to {path} failed too ({err}): the run is not recorded"
        return s
    s.warning = f"{failure}; the recording is saved to {path} instead (python -m windowvo.view {path.parent})"
    return s


def _save(s: OpenedSink, path: Path, bp: rrb.Blueprint) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SinkFailed(f"cannot create {path.parent} ({err.strerror})") from None
    check_disk(path)
    try:
        s.rec.save(str(path), default_blueprint=bp)
    except RuntimeError as err:
        close_stream(s.rec)
        remove_partial(path)
        raise SinkFailed(f"cannot write {path} ({err})") from None
    s.path, s.kind = path, SinkKind.FILE


def _open_live(s: OpenedSink, mode: RerunMode, target: ConnectTarget | None, bp: rrb.Blueprint) -> None:
    if mode is RerunMode.SPAWN:
        s.viewer_process = spawn_viewer(SPAWN_PORT)
        target = ConnectTarget(f"rerun+http://127.0.0.1:{SPAWN_PORT}/proxy", "127.0.0.1", SPAWN_PORT)
    if target is not None:
        reason = port_answers(target.host, target.port)
        if reason is not None:
            raise SinkFailed(f"no Rerun viewer answers at {target.host}:{target.port} ({reason})")
        _bounded_call(lambda: s.rec.connect_grpc(target.url, default_blueprint=bp),
                           f"connecting to {target.url}")
        s.kind = SinkKind.VIEWER
    elif mode is RerunMode.SERVE:
        for port in (SPAWN_PORT, WEB_PORT):
            if not port_free(port):
                raise SinkFailed(f"port {port} is taken (another Rerun viewer or server?), cannot serve")
        uris: list[str] = []
        _bounded_call(lambda: uris.append(s.rec.serve_grpc(default_blueprint=bp)), "serving gRPC")
        _bounded_call(lambda: rr.serve_web_viewer(web_port=WEB_PORT, connect_to=uris[0], open_browser=False),
                           "serving the web viewer")
        s.kind = SinkKind.SERVER
        log.info("Rerun web viewer at http://127.0.0.1:%d (recording %s)", WEB_PORT, uris[0])


def _bounded_call(fn: Callable[[], Any], what: str) -> None:
    done, err = bounded(fn, CONNECT_PROBE_S + 5.0, "windowvo-rerun-open")
    if not done:
        raise SinkFailed(f"{what} took more than {CONNECT_PROBE_S + 5.0:.0f} s")
    if err is not None:
        raise SinkFailed(f"{what} failed ({err})")

