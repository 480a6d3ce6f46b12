"""Faults driven through the real command line (``python -m windowvo.run``) in subprocesses: real signals at chosen
points, SIGKILL and --resume, a second run into a used folder, two runs at once, bad calibration, teleporting wheels.
Each asserts the exit code, the one-line message, no traceback, and what is on disk afterwards.

Signals "at a chosen point" are either sent from outside once the run's journal shows progress, or sent by the run
to itself from a patched step (``_injected``): the CLI's own code path, with the signal landing exactly there."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from windowvo.io.trajectory import read_tum
from windowvo.runtime.journal import JOURNAL_NAME, last_final_frame, read_journal

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
TIMEOUT = 120


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    """A small rendered sequence: 161 frames of 160x120 with wheel odometry and ground truth."""
    d = tmp_path_factory.mktemp("faults") / "seq"
    subprocess.run([sys.executable, "-m", "windowvo.synth", str(d), "--duration", "8", "--width", "160", "--height",
                    "120"], check=True, env=ENV, capture_output=True, timeout=TIMEOUT)
    return d


def config(path: Path, seq: Path, out: Path, **extra: str) -> Path:
    # A short fixed-lag window: keyframes become final (marginalised) early in the short sequence.
    lines = [f"sequence: {seq}", f"output: {out}", "viz:", "  rerun: 'off'", "backend:", "  window_keyframes: 8"]
    lines += [f"{k}: {v}" for k, v in extra.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def cli(*args: str, timeout: float = TIMEOUT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "windowvo.run", *args, "--no-progress", "-q"], capture_output=True,
                          text=True, env=ENV, timeout=timeout)


def one_line_error(r: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in r.stderr, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("windowvo")]
    assert len(errors) == 1, r.stderr
    return errors[0]


def n_poses(path: Path) -> int:
    return sum(1 for ln in path.read_text().splitlines() if ln and not ln.startswith("#"))


def n_rows(path: Path) -> int:
    return len(path.read_text().splitlines()) - 1


def _injected(module: str, attr: str, signame: str, args: list[str]) -> subprocess.CompletedProcess:
    """The CLI with ``module.attr`` patched to send ``signame`` to the process just before it runs."""
    code = textwrap.dedent(f"""
        import os, signal, sys
        import windowvo.run  # installs the stop handlers first, as `python -m windowvo.run` does
        import {module} as m
        orig = getattr(m, {attr!r})
        def patched(*a, **k):
            os.kill(os.getpid(), signal.{signame})
            return orig(*a, **k)
        setattr(m, {attr!r}, patched)
        sys.exit(windowvo.run.main({args + ["--no-progress", "-q"]!r}))
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=TIMEOUT)


@pytest.fixture(scope="module")
def reference(seq, tmp_path_factory):
    """An uninterrupted pipelined run, in its own session: after it exits, no process of its group may be left."""
    d = tmp_path_factory.mktemp("reference")
    cfg = config(d / "c.yaml", seq, d / "out")
    proc = subprocess.Popen([sys.executable, "-m", "windowvo.run", str(cfg), "--no-progress", "-q"], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    _, err = proc.communicate(timeout=TIMEOUT)
    left = [p.name for p in Path("/proc").iterdir() if p.name.isdigit() and _pgrp(p) == proc.pid]
    assert proc.returncode == 0, err
    return cfg, d / "out", left


def _pgrp(p: Path) -> int | None:
    try:
        return int(p.joinpath("stat").read_text().rsplit(")", 1)[1].split()[2])
    except (OSError, IndexError, ValueError):
        return None


@pytest.mark.slow
def test_the_run_leaves_no_process_in_its_group(reference):
    _, out, left = reference
    assert (out / "summary.json").is_file()
    assert left == []


def _handles_sigterm(pid: int) -> bool:
    """The process has a SIGTERM handler: windowvo's stop handlers are in (Python installs none of its own)."""
    for ln in Path(f"/proc/{pid}/status").read_text().splitlines():
        if ln.startswith("SigCgt:"):
            return bool(int(ln.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    return False


@pytest.mark.parametrize("delay_s", [0.0, 0.8])
def test_sigint_during_imports_or_loading_is_one_line_exit_130(seq, tmp_path, delay_s):
    """SIGINT at once after the handlers are in (the imports of the command line follow), or a little later."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "windowvo.run", str(config(tmp_path / "c.yaml", seq, out)),
                             "--no-progress"], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while proc.poll() is None and not _handles_sigterm(proc.pid) and time.monotonic() - t0 < TIMEOUT:
        time.sleep(0.001)
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=TIMEOUT)
    assert proc.returncode == 130, err
    assert "Traceback" not in err, err
    if "interrupted after frame" in err:  # a fast machine is in the frame loop 0.8 s in: what ran is written
        assert delay_s > 0 and (out / "trajectory.txt").is_file(), err
    else:  # before the first frame: one line, nothing written (loading alone: the next test)
        assert "interrupted by SIGINT" in err, err
        assert not (out / "trajectory.txt").exists()


def test_sigint_while_loading_is_one_line_exit_130(seq, tmp_path):
    out = tmp_path / "out"
    r = _injected("windowvo.runtime.job", "load_sequence", "SIGINT", [str(config(tmp_path / "c.yaml", seq, out))])
    assert r.returncode == 130
    assert "interrupted by SIGINT before the first frame" in one_line_error(r)
    assert not (out / "summary.json").exists()


def test_sigterm_in_the_frame_loop_writes_every_finished_frame(seq, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "windowvo.run", str(config(tmp_path / "c.yaml", seq, out)),
                             "--no-progress"], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while proc.poll() is None and _journal_frames(out) < 30 and time.monotonic() - t0 < TIMEOUT:
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=TIMEOUT)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True
    n = summary["frames"]
    assert 30 <= n < 161
    assert n_poses(out / "trajectory.txt") == n_rows(out / "stats.csv") == n
    assert (out / "config_resolved.yaml").is_file()


def _journal_frames(out: Path) -> int:
    try:
        return (out / JOURNAL_NAME).read_text().count('{"frame"')
    except OSError:
        return 0


@pytest.mark.parametrize(("where", "signame", "code"), [
    ("windowvo.runtime.parallel:BackendWorker.finish", "SIGINT", 130),  # the back end draining (pipelined)
    ("windowvo.runtime.job:write_outputs", "SIGTERM", 143),  # all frames done, writing the outputs
])
def test_a_signal_after_the_last_frame_keeps_the_finished_run(seq, tmp_path, where, signame, code):
    module, attr = where.split(":")
    args = [str(config(tmp_path / "c.yaml", seq, tmp_path / "out"))]
    if "." in attr:  # a method: patch it on its class
        cls, meth = attr.split(".")
        r = _injected_method(module, cls, meth, signame, args)
    else:
        r = _injected(module, attr, signame, args)
    assert r.returncode == code, r.stderr
    assert "Traceback" not in r.stderr
    out = tmp_path / "out"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True and summary["frames"] == 161
    assert summary["accuracy"]["ate_se3_rmse_m"] < 0.1
    assert n_poses(out / "trajectory.txt") == n_rows(out / "stats.csv") == 161


def _injected_method(module: str, cls: str, meth: str, signame: str, args: list[str]) -> subprocess.CompletedProcess:
    code = textwrap.dedent(f"""
        import os, signal, sys
        import windowvo.run
        import {module} as m
        klass = getattr(m, {cls!r})
        orig = getattr(klass, {meth!r})
        def patched(self, *a, **k):
            os.kill(os.getpid(), signal.{signame})
            return orig(self, *a, **k)
        setattr(klass, {meth!r}, patched)
        sys.exit(windowvo.run.main({args + ["--no-progress", "-q"]!r}))
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=TIMEOUT)


def _kill_when(cmd: list[str], out: Path, n_frames: int) -> None:
    """Run ``python -m windowvo.run CMD`` in its own session, SIGKILL its group once the journal holds n_frames."""
    proc = subprocess.Popen([sys.executable, "-m", "windowvo.run", *cmd, "--no-progress", "-q"], env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    t0 = time.monotonic()
    while proc.poll() is None and _journal_frames(out) < n_frames and time.monotonic() - t0 < TIMEOUT:
        time.sleep(0.002)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=TIMEOUT)


@pytest.fixture(scope="module")
def killed(seq, tmp_path_factory):
    """A run killed by SIGKILL once its journal held 100 frames (tests resume copies of the folder)."""
    d = tmp_path_factory.mktemp("killed")
    out = d / "out"
    _kill_when([str(config(d / "c.yaml", seq, out))], out, 100)
    return out


def _copy_killed(killed: Path, seq: Path, tmp_path: Path) -> tuple[Path, Path]:
    out = tmp_path / "out"
    shutil.copytree(killed, out)
    return config(tmp_path / "c.yaml", seq, out), out


def _ate(out: Path) -> float:
    return json.loads((out / "summary.json").read_text())["accuracy"]["ate_se3_rmse_m"]


def _assert_whole_sequence(out: Path, ref_out: Path) -> dict:
    """The resumed folder covers every frame of the sequence, as accurately as the uninterrupted run (1.05x)."""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resumed"] is True and summary["interrupted"] is False
    assert summary["frames"] == n_poses(out / "trajectory.txt") == n_rows(out / "stats.csv") == 161
    assert n_poses(out / "trajectory_online.txt") == 161
    frames = [int(ln.split(",")[0]) for ln in (out / "stats.csv").read_text().splitlines()[1:]]
    assert frames == list(range(161))
    assert _ate(out) <= 1.05 * _ate(ref_out), (_ate(out), _ate(ref_out))
    # The replay is the killed run (deterministic), and the resumed trajectory the uninterrupted one's.
    assert summary["replay_max_difference_m"] == 0.0, summary
    traj, ref = (np.loadtxt(d / "trajectory.txt", comments="#") for d in (out, ref_out))
    np.testing.assert_allclose(traj[:, 1:4], ref[:, 1:4], atol=1e-9)
    return summary


@pytest.mark.slow
def test_sigkill_then_resume_continues_to_the_end(seq, tmp_path, reference, killed):
    _, ref_out, _ = reference
    cfg, out = _copy_killed(killed, seq, tmp_path)
    j = read_journal(out / JOURNAL_NAME)
    last = last_final_frame(j)
    assert last is not None and len(j.records) >= 100
    assert not (out / "trajectory.txt").exists()
    r = cli(str(cfg), "--resume")
    assert r.returncode == 0, r.stderr
    summary = _assert_whole_sequence(out, ref_out)
    assert summary["resumed_from_frame"] == j.records[last].frame_index
    traj, ref = read_tum(out / "trajectory.txt"), read_tum(ref_out / "trajectory.txt")
    # Every frame up to the last marginalised keyframe has the uninterrupted run's smoothed pose.
    np.testing.assert_allclose(traj.T_world_base[: last + 1], ref.T_world_base[: last + 1], atol=1e-6)
    assert (out / "config_resolved.yaml").is_file()
    again = cli(str(cfg), "--resume")
    assert again.returncode == 2 and "nothing to resume" in one_line_error(again)


@pytest.mark.slow
def test_a_kill_during_resume_is_resumed_again(seq, tmp_path, reference, killed):
    _, ref_out, _ = reference
    cfg, out = _copy_killed(killed, seq, tmp_path)
    n_before = _journal_frames(out)
    _kill_when([str(cfg), "--resume"], out, n_before + 130)  # 130 frames into the continuation (from frame 0)
    j = read_journal(out / JOURNAL_NAME)
    assert len(j.resumed_from) == 1 and j.end is None and len(j.records) >= n_before
    r = cli(str(cfg), "--resume")
    assert r.returncode == 0, r.stderr
    _assert_whole_sequence(out, ref_out)
    assert len(read_journal(out / JOURNAL_NAME).resumed_from) == 2


@pytest.mark.slow
def test_sigterm_during_resume_writes_the_frames_so_far_and_resumes_again(seq, tmp_path, reference, killed):
    _, ref_out, _ = reference
    cfg, out = _copy_killed(killed, seq, tmp_path)
    code = textwrap.dedent(f"""
        import os, signal, sys
        import windowvo.run
        from windowvo.runtime.pipeline import Pipeline
        orig, calls = Pipeline._step, []
        def patched(self, *a, **k):  # SIGTERM at the continuation's 130th frame (it starts before the seam)
            calls.append(1)
            if len(calls) == 130:
                os.kill(os.getpid(), signal.SIGTERM)
            return orig(self, *a, **k)
        Pipeline._step = patched
        sys.exit(windowvo.run.main({[str(cfg), "--resume", "--no-progress", "-q"]!r}))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=TIMEOUT)
    assert r.returncode == 143, r.stderr
    assert "Traceback" not in r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resumed"] is True and summary["interrupted"] is True
    assert len(read_journal(killed / JOURNAL_NAME).records) <= summary["frames"] < 161  # nothing finished is lost
    assert n_poses(out / "trajectory.txt") == n_rows(out / "stats.csv") == summary["frames"]
    again = cli(str(cfg), "--resume")
    assert again.returncode == 0, again.stderr
    _assert_whole_sequence(out, ref_out)


def test_a_second_run_into_a_used_folder_is_refused(reference):
    cfg, out, _ = reference
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    r = cli(str(cfg))
    assert r.returncode == 2
    assert "--force" in one_line_error(r)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


def test_force_moves_the_old_run_aside_and_a_failed_run_leaves_no_stale_summary(seq, tmp_path, reference):
    _, ref_out, _ = reference
    out = tmp_path / "out"
    shutil.copytree(ref_out, out)
    black = tmp_path / "black"
    shutil.copytree(seq, black)
    for img in (black / "images").iterdir():
        cv2.imwrite(str(img), np.zeros((120, 160), np.uint8))
    r = cli(str(config(tmp_path / "c.yaml", black, out)), "--force")
    assert r.returncode == 2
    assert "no keyframe" in one_line_error(r)
    assert not (out / "summary.json").exists()
    (old,) = out.glob("previous-*")
    assert n_poses(old / "trajectory.txt") == 161 and (old / "summary.json").is_file()
    assert n_poses(old / "trajectory_online.txt") == 161
    assert len(read_journal(old / JOURNAL_NAME).records) == 161  # the old journal moved whole, not truncated


def test_a_second_concurrent_run_names_the_first_pid(seq, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import fcntl, os, sys, time
        fh = open({str(out / '.windowvo.lock')!r}, 'a+'); fcntl.flock(fh, fcntl.LOCK_EX)
        fh.write(str(os.getpid())); fh.flush(); print('locked', flush=True); time.sleep(60)
    """)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        r = cli(str(config(tmp_path / "c.yaml", seq, out)))
    finally:
        holder.kill()
        holder.wait(timeout=TIMEOUT)
    assert r.returncode == 2
    assert f"PID {holder.pid}" in one_line_error(r)
    assert not (out / JOURNAL_NAME).exists()


def test_a_stale_lock_of_a_dead_process_is_taken_over(seq, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          timeout=TIMEOUT)
    (out / ".windowvo.lock").write_text(dead.stdout)
    with (out / ".windowvo.lock").open() as fh:  # nobody holds it
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fh, fcntl.LOCK_UN)
    r = cli(str(config(tmp_path / "c.yaml", seq, out, max_frames="20")))
    assert r.returncode == 0, r.stderr
    assert n_poses(out / "trajectory.txt") == 20


def test_a_directory_named_trajectory_txt_is_refused_before_the_run(seq, tmp_path):
    out = tmp_path / "out"
    (out / "trajectory.txt").mkdir(parents=True)
    t0 = time.monotonic()
    r = cli(str(config(tmp_path / "c.yaml", seq, out)))
    assert r.returncode == 2
    assert "trajectory.txt" in one_line_error(r)
    assert not (out / JOURNAL_NAME).exists() and time.monotonic() - t0 < 30


def test_a_reflected_T_base_cam_is_refused(seq, tmp_path):
    bad = tmp_path / "seq"
    shutil.copytree(seq, bad, ignore=shutil.ignore_patterns("images"))
    (bad / "images").symlink_to(seq / "images")
    text = (bad / "camera.yaml").read_text()
    start = text.index("T_base_cam:")
    T = np.eye(4)
    T[1, 1] = -1.0
    (bad / "camera.yaml").write_text(text[:start] + f"T_base_cam: {[float(v) for v in T.ravel()]}\n")
    r = cli(str(config(tmp_path / "c.yaml", bad, tmp_path / "out")))
    assert r.returncode == 2
    assert "reflection" in one_line_error(r)


def test_one_frame_says_so(seq, tmp_path):
    one = tmp_path / "seq"
    shutil.copytree(seq, one)
    for img in sorted((one / "images").iterdir())[1:]:
        img.unlink()
    (one / "times.txt").write_text((seq / "times.txt").read_text().splitlines()[0] + "\n")
    r = cli(str(config(tmp_path / "c.yaml", one, tmp_path / "out")))
    assert r.returncode == 2
    assert "one frame" in one_line_error(r)


def test_teleporting_wheels_are_rejected_with_a_warning(seq, tmp_path, reference):
    _, ref_out, _ = reference
    tele = tmp_path / "seq"
    shutil.copytree(seq, tele, ignore=shutil.ignore_patterns("images"))
    (tele / "images").symlink_to(seq / "images")
    lines, k = [], 0
    for ln in (seq / "odometry.csv").read_text().splitlines():
        if ln[:1].isdigit():
            k += 1
            if k >= 300:  # from 3 s on, the wheels report the base 1000 m further along x
                t, x, y, yaw = ln.split(",")
                ln = f"{t},{float(x) + 1000.0:.6f},{y},{yaw}"
        lines.append(ln)
    (tele / "odometry.csv").write_text("\n".join(lines) + "\n")
    r = cli(str(config(tmp_path / "c.yaml", tele, tmp_path / "out")))
    assert r.returncode == 0, r.stderr
    assert "wheel odometry jumps 1000.0 m" in r.stderr and "Traceback" not in r.stderr
    ate = json.loads((tmp_path / "out" / "summary.json").read_text())["accuracy"]["ate_se3_rmse_m"]
    ref_ate = json.loads((ref_out / "summary.json").read_text())["accuracy"]["ate_se3_rmse_m"]
    assert ate < max(2.0 * ref_ate, 0.05)


def test_a_stop_during_a_compiled_modules_import_is_a_stop_not_an_error(monkeypatch, capsys):
    """SIGINT while gtsam's extension initialises surfaces as "ImportError: initialization failed" (seen in
    test_sigint_during_imports_or_loading_is_one_line_exit_130 on a loaded machine): exit 130 and one line."""
    from windowvo.cli import run as cli_run
    from windowvo.runtime import stop

    def import_hit_by_sigint(argv):
        stop.STATE.signum = signal.SIGINT  # what the handler records, before the extension re-raises
        raise ImportError("initialization failed")

    def plain_import_error(argv):
        raise ImportError("no module named gtsam")

    try:
        monkeypatch.setattr(cli_run, "_main", import_hit_by_sigint)
        assert cli_run.main([]) == 130
        assert "interrupted by SIGINT" in capsys.readouterr().err
        stop.uninstall()
        monkeypatch.setattr(cli_run, "_main", plain_import_error)
        with pytest.raises(ImportError):  # without a stop signal an ImportError is not hidden
            cli_run.main([])
    finally:
        stop.uninstall()
