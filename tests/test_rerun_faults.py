"""Rerun sinks that fail: the real command lines, in subprocesses with a hard timeout, never hang and never
print a traceback; the run says what happened in one warning line and writes its outputs.

Each case runs ``python -m windowvo.run`` (or ``windowvo.view``) in a session of its own; this test
process becomes the child subreaper (Linux), so a viewer the CLI left behind would be re-parented here and
is looked for afterwards.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from windowvo.synth.paths import PathKind

ROOT = Path(__file__).resolve().parents[1]
RUN_TIMEOUT_S = 45.0  # a run of this sequence takes ~3 s; the slowest failure (a mute viewer) ~12 s
PR_SET_CHILD_SUBREAPER = 36


@dataclass
class Ran:
    code: int
    stderr: str
    stdout: str
    out: Path

    @property
    def sink_warnings(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.startswith("WARNING windowvo.viz")]


@pytest.fixture(scope="module")
def sequence(seq_factory) -> Path:
    return seq_factory("faults_loop", path=PathKind.LOOP, duration_s=3.0, seed=5, width=320, height=240)


@pytest.fixture(autouse=True)
def one_at_a_time(tmp_path_factory):
    """These tests use rerun's fixed ports (9876, 9090) and look for leftover viewers: never two of them at once,
    across the xdist workers (a spawned viewer on 9876 beside a served web viewer made `--web` + Ctrl-C hang)."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    with open(root / "rerun_ports.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


@pytest.fixture(scope="module")
def subreaper() -> bool:
    """Make this process the reaper of orphans from the CLI, so leftover viewers can be found."""
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    return libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0


def _children() -> list[tuple[int, str]]:
    """(pid, command line) of this process's children other than the test runner's own."""
    me = os.getpid()
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            stat = (d / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == me:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
                found.append((int(d.name), cmd or stat.split()[1]))
    return found


def _env(**changes: str | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    for k, v in changes.items():
        if v is None:
            env.pop(k, None)
        else:
            env[k] = v
    return env


def _run(argv: list[str], out: Path, env: dict[str, str] | None = None,
         timeout: float = RUN_TIMEOUT_S, subreaper: bool = False) -> Ran:
    before = {pid for pid, _ in _children()}
    proc = subprocess.Popen([sys.executable, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env or _env(), start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        pytest.fail(f"{' '.join(argv)} hung (> {timeout:.0f} s); stderr ends:\n{stderr[-2000:]}")
    if subreaper:
        time.sleep(0.2)
        left = [(pid, cmd) for pid, cmd in _children() if pid not in before]
        for pid, _ in left:  # clean up before failing
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
            with contextlib.suppress(OSError):
                os.waitpid(pid, 0)
        assert not left, f"processes left behind by the CLI: {left}"
    return Ran(proc.returncode, stderr, stdout, out)


def _run_vo(sequence: Path, out: Path, *overrides: str, env: dict[str, str] | None = None,
            subreaper: bool = False) -> Ran:
    # A config file names the sequence (overrides alone would render the default sequence first).
    out.parent.mkdir(parents=True, exist_ok=True)
    cfg = out.parent / f"{out.name}.yaml"
    cfg.write_text(f"sequence: {sequence}\noutput: {out}\nrun_mode: sequential\n")
    argv = ["-m", "windowvo.run", "--no-progress", str(cfg), *overrides]
    return _run(argv, out, env=env, subreaper=subreaper)


def _assert_survived(r: Ran, *words: str, recorded: bool) -> str:
    """Exit 0, no traceback, exactly one warning about the sink (holding ``words``), the outputs written,
    and OUTPUT/recording.rrd there exactly when ``recorded``. Returns the warning."""
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    assert r.code == 0, r.stderr[-3000:]
    assert len(r.sink_warnings) == 1, r.stderr[-3000:]
    warning = r.sink_warnings[0]
    for w in words:
        assert w in warning, warning
    assert (r.out / "summary.json").is_file()
    assert (r.out / "trajectory.txt").stat().st_size > 0
    assert (r.out / "recording.rrd").is_file() == recorded, warning
    if recorded:
        assert (r.out / "recording.rrd").stat().st_size > 10_000
    return warning


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_connect_to_a_dead_port_falls_back_to_saving(sequence, tmp_path, subreaper):
    url = f"rerun+http://127.0.0.1:{_free_port()}/proxy"
    r = _run_vo(sequence, tmp_path / "o", "viz.rerun=connect", f"viz.connect_url={url}", subreaper=subreaper)
    _assert_survived(r, "viz.rerun=connect", "no Rerun viewer answers", "saved to", recorded=True)


@pytest.mark.slow
def test_connect_to_a_mute_viewer_is_bounded(sequence, tmp_path, subreaper):
    """Something accepts the connection but never speaks gRPC: the end of the run waits a bounded time."""
    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(8)
        url = f"rerun+http://127.0.0.1:{srv.getsockname()[1]}/proxy"
        r = _run_vo(sequence, tmp_path / "o", "viz.rerun=connect", f"viz.connect_url={url}", subreaper=subreaper)
    _assert_survived(r, "viz.rerun=connect", "did not reach", recorded=False)


def test_malformed_connect_url_is_one_line(sequence, tmp_path):
    r = _run_vo(sequence, tmp_path / "o", "viz.rerun=connect", "viz.connect_url=notaurl")
    assert r.code == 2, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("windowvo: error:")]
    assert len(errors) == 1 and "viz.connect_url" in errors[0] and "/proxy" in errors[0], r.stderr[-3000:]


def test_spawn_without_a_display_falls_back_to_saving(sequence, tmp_path, subreaper):
    r = _run_vo(sequence, tmp_path / "o", "viz.rerun=spawn", subreaper=subreaper)
    _assert_survived(r, "viz.rerun=spawn", "no display", "saved to", recorded=True)


@pytest.mark.slow
def test_spawned_viewer_that_dies_is_reaped(sequence, tmp_path, subreaper):
    """DISPLAY names an X server that does not exist: the viewer starts, listens, then cannot open its window."""
    if Path("/tmp/.X11-unix/X99").exists():
        pytest.skip("an X server runs at :99")
    with socket.socket() as s:
        try:
            s.bind(("0.0.0.0", 9876))
        except OSError:
            pytest.skip("port 9876 is taken (a Rerun viewer runs here): spawning would connect to it")
    r = _run_vo(sequence, tmp_path / "o", "viz.rerun=spawn", env=_env(DISPLAY=":99"), subreaper=subreaper)
    _assert_survived(r, "viz.rerun=spawn", "viewer exited", "saved to", recorded=True)


@pytest.fixture
def small_disk(tmp_path):
    """A 256 KiB tmpfs (root only; skipped otherwise)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    mount = shutil.which("mount")
    if mount is None or subprocess.run([mount, "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)],
                                       capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    yield mnt
    subprocess.run(["umount", str(mnt)], capture_output=True)


def test_save_on_a_full_disk_keeps_the_other_outputs(sequence, small_disk):
    r = _run_vo(sequence, small_disk / "o", "viz.rerun=save")
    _assert_survived(r, "viz.rerun=save", "MiB left", recorded=False)


def test_view_without_a_display_says_use_web(sequence, tmp_path):
    rrd = tmp_path / "some.rrd"
    rrd.write_bytes(b"not read: the display is checked first")
    r = _run(["-m", "windowvo.view", str(rrd)], tmp_path, timeout=30.0)
    assert r.code == 2, r.stderr[-3000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("windowvo.view: error:") and "--web" in lines[0], r.stderr


def _terminal_sigint() -> None:
    """In the child before it starts: Ctrl-C as a terminal's program gets it (default action, not blocked), whatever
    the test worker's threads inherited (a worker process started beside them blocks it for a moment)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _signal_state(pid: int) -> str:
    """The kernel's view of a process's signals (blocked, ignored, caught), for a failure message."""
    with contextlib.suppress(OSError):
        return " ".join(line for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                        if line.startswith(("SigBlk", "SigIgn", "SigCgt")))
    return "(gone)"


@pytest.mark.slow
def test_view_web_ctrl_c_exits_130(sequence, tmp_path):
    r0 = _run_vo(sequence, tmp_path / "o", "viz.rerun=save", "max_frames=10")
    assert (r0.out / "recording.rrd").is_file(), r0.stderr[-3000:]
    port = 9090
    with socket.socket() as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            pytest.skip("port 9090 is taken: the web viewer cannot be served here")
    proc = subprocess.Popen([sys.executable, "-m", "windowvo.view", str(r0.out), "--web"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(), start_new_session=True,
                            preexec_fn=_terminal_sigint)
    try:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and proc.poll() is None:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        state = _signal_state(proc.pid)
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole foreground group
        try:
            _out, err = proc.communicate(timeout=20.0)
        except subprocess.TimeoutExpired:
            pytest.fail(f"windowvo.view --web did not end within 20 s of Ctrl-C; its signals then: {state}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):  # bounded: a leftover could hold the pipes
                proc.communicate(timeout=10.0)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_stopping_the_viewer_stops_what_it_started(tmp_path):
    """A viewer whose launcher starts a process that ignores Ctrl-C (as a busy viewer binary may): the stop
    reaches and ends that process too, within the bounded waits, not only the launcher."""
    from windowvo.viz import viewer

    pid_file = tmp_path / "grandchild.pid"
    launcher = ("import subprocess, sys, time\n"
                "c = subprocess.Popen([sys.executable, '-c', 'import signal, time; "
                "signal.signal(signal.SIGINT, signal.SIG_IGN); time.sleep(120)'])\n"
                f"open({str(pid_file)!r}, 'w').write(str(c.pid))\n"
                "time.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", launcher])
    deadline = time.monotonic() + 20.0
    while not (pid_file.is_file() and pid_file.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    grandchild = int(pid_file.read_text())
    assert _alive(grandchild)
    t0 = time.monotonic()
    viewer._stop(proc, [])
    assert time.monotonic() - t0 <= 2 * viewer.STOP_WAIT_S + 2.0
    assert proc.poll() is not None
    deadline = time.monotonic() + 5.0
    while _alive(grandchild) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(grandchild)
