"""The pipelined run (back end in a worker process) gives the sequential run's results bit for bit."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
from conftest import make_config

from windowvo.errors import WindowVOError
from windowvo.runtime.job import run_job
from windowvo.runtime.outputs import floor_summary
from windowvo.runtime.parallel import BackendWorker
from windowvo.synth.paths import PathKind


@pytest.mark.slow
@pytest.mark.parametrize("case", ["level", "rocking_tilted_mount", "tilted_mount_auto", "monocular_floor_late"])
def test_pipelined_equals_sequential(short_loop, seq_factory, tmp_path, case):
    """Also on a rocking base whose camera.yaml is 0.5 deg off, with the mount calibration on: the level
    frame's Python factor and the learnt floor normal are built in the worker process; and on a loop whose
    camera.yaml is 1 deg off with the default (auto): the switch re-ties floor landmarks in the worker; and a
    monocular run that sees the floor only after 2 s: the late metric start rescales the trajectory in the worker."""
    seq, backend = short_loop, {}
    if case == "rocking_tilted_mount":
        seq = seq_factory("short_rocking_tilted", path=PathKind.FIGURE_EIGHT, duration_s=12.0, seed=8,
                          vibration_deg=1.0, calib_pitch_error_deg=0.5)
        backend = {"ground": {"mount_calibration": True}}
    if case == "tilted_mount_auto":
        # short_loop's images (tests/conftest.py shares the render) with a camera.yaml 1 deg off
        seq = seq_factory("short_tilted", path=PathKind.LOOP, duration_s=12.0, seed=5, calib_pitch_error_deg=1.0)
    if case == "monocular_floor_late":
        seq = seq_factory("short_floor_late", path=PathKind.LOOP, duration_s=12.0, seed=5, floor_hidden_frames=40)
        backend = {"use_odometry": False}
    reps = {}
    for mode in ("sequential", "pipelined"):
        reps[mode] = run_job(make_config(seq, tmp_path / mode, run_mode=mode, backend=backend))
    floor = floor_summary(reps["pipelined"].result.records)
    if case == "rocking_tilted_mount":
        assert floor["level_frame_keyframes"] > 0 and floor["floor_tilt_deg"] is not None, floor
    if case == "tilted_mount_auto":
        assert floor["floor_normal_learnt_keyframes"] > 0, floor
    for name in ("trajectory.txt", "trajectory_online.txt"):
        a = (tmp_path / "sequential" / name).read_text()
        b = (tmp_path / "pipelined" / name).read_text()
        assert a == b, name
    seq, pip = reps["sequential"].result, reps["pipelined"].result
    assert (seq.n_keyframes, seq.n_resets, seq.metric, seq.scale_sources, seq.metric_from_frame,
            seq.floor_scale_reanchors, seq.floor_untied, seq.floor_beside_track) == (
        pip.n_keyframes, pip.n_resets, pip.metric, pip.scale_sources, pip.metric_from_frame,
        pip.floor_scale_reanchors, pip.floor_untied, pip.floor_beside_track)
    if case == "monocular_floor_late":
        assert pip.metric and pip.metric_from_frame is not None and pip.metric_from_frame >= 40, pip
    else:
        assert seq.wheel_calibration is not None and pip.wheel_calibration is not None
        assert seq.wheel_calibration.scale == pip.wheel_calibration.scale
    # per-frame statistics agree too, apart from timings
    rows_s = (tmp_path / "sequential" / "stats.csv").read_text().splitlines()
    rows_p = (tmp_path / "pipelined" / "stats.csv").read_text().splitlines()
    assert len(rows_s) == len(rows_p) == len(reps["sequential"].sequence) + 1
    header = rows_s[0].split(",")
    keep = [i for i, h in enumerate(header) if not h.endswith("_ms")]
    for rs, rp in zip(rows_s[1:], rows_p[1:]):
        fs, fp = rs.split(","), rp.split(",")
        assert [fs[i] for i in keep] == [fp[i] for i in keep]
    assert reps["pipelined"].accuracy.ate_se3_rmse_m == reps["sequential"].accuracy.ate_se3_rmse_m


def test_a_dead_worker_is_one_clear_error():
    w = BackendWorker()
    try:
        os.kill(w.pid, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while w.alive and time.monotonic() < deadline:
            time.sleep(0.05)
        try:
            w.result(block=True)
        except WindowVOError as err:
            assert "back-end process died" in str(err)
        else:  # pragma: no cover
            raise AssertionError("no error for a dead worker")
    finally:
        w.close()


def test_summary_says_how_it_ran(short_loop, tmp_path):
    from windowvo.runtime.job import run_and_report

    run_and_report(make_config(short_loop, tmp_path / "p", run_mode="pipelined", max_frames=60))
    summary = json.loads((tmp_path / "p" / "summary.json").read_text())
    assert summary["run_mode"] == "pipelined"
    assert summary["frames"] == 60


_ORPHAN_SCRIPT = """
import os, sys, time
from windowvo.config import BackendConfig
from windowvo.runtime.parallel import BackendWorker
from windowvo.synth.features import simulate_features
from windowvo.synth.generate import SynthSpec
from windowvo.synth.paths import PathKind

if __name__ == "__main__":
    fs = simulate_features(SynthSpec(path=PathKind.LOOP, duration_s=15.0, speed=0.8, seed=3))
    w = BackendWorker()
    w.start(fs.world.camera, BackendConfig(), use_odometry=False)
    for fo in fs.keyframes[:40]:
        w.submit(fo, None)  # results never read: the worker's pipe to this process fills up
    print(w.pid, flush=True)
    time.sleep(60)
"""


_CUT_MESSAGE_SCRIPT = """
import os, struct, sys, time
from windowvo.runtime.parallel import BackendWorker

if __name__ == "__main__":
    w = BackendWorker()
    print(w.pid, flush=True)
    time.sleep(float(sys.argv[1]))  # the worker has started and waits for its first message
    # A message cut short, as a feeder thread killed while writing a keyframe's image leaves it: the header
    # promises a megabyte, 100 bytes follow, and nothing more will come.
    os.write(w._inbox._writer.fileno(), struct.pack("!i", 1 << 20) + b"x" * 100)
    print("cut", flush=True)
    time.sleep(60)
"""


def _kill_main_and_wait_for_worker(tmp_path, script_text: str, args: list[str], settle_s: float) -> bool:
    """Run ``script_text`` (it prints its worker's pid first), SIGKILL it after ``settle_s``; True when the worker
    outlived it by 15 s (it is then killed here)."""
    import subprocess
    import sys

    script = tmp_path / "main.py"
    script.write_text(script_text)
    p = subprocess.Popen([sys.executable, str(script), *args], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                         text=True)
    worker_pid = int(p.stdout.readline())
    time.sleep(settle_s)
    p.send_signal(signal.SIGKILL)
    p.wait(timeout=10)
    deadline = time.time() + 15.0
    alive = True
    while time.time() < deadline and alive:
        try:
            os.kill(worker_pid, 0)
            with open(f"/proc/{worker_pid}/stat") as f:
                alive = f.read().split()[2] != "Z"
        except (ProcessLookupError, FileNotFoundError):
            alive = False
        time.sleep(0.2)
    if alive:
        os.kill(worker_pid, signal.SIGKILL)
    return alive


@pytest.mark.slow
def test_the_worker_ends_when_the_main_process_is_killed(tmp_path):
    """SIGKILL of the main process while the worker holds unread results (more than a pipe's buffer):
    the worker must still end (an orphan would keep the robot's CPU and the parent's output pipes)."""
    # the worker processes the 40 keyframes within the 8 s, its results pile up unread
    assert not _kill_main_and_wait_for_worker(tmp_path, _ORPHAN_SCRIPT, [], 8.0), \
        "the back-end worker outlived the killed main process"


@pytest.mark.slow
def test_the_worker_ends_when_the_main_process_is_killed_mid_message(tmp_path):
    """SIGKILL of the main process in the middle of writing a keyframe's message: the worker, blocked reading the
    rest of it (it holds a copy of the pipe's write end, so no end of file comes), must still end. Found by
    tests/test_stream.py's SIGKILL test once the keyframes' images went to the worker: an orphan that kept the
    run's stdout open, so the parent waiting for it hung."""
    assert not _kill_main_and_wait_for_worker(tmp_path, _CUT_MESSAGE_SCRIPT, ["4"], 6.0), \
        "the back-end worker outlived the killed main process"


def test_opencv_threads_change_no_result_and_are_put_back(short_loop, tmp_path):
    """``opencv_threads`` only moves OpenCV's work between threads: 1 gives the same trajectory as OpenCV's own thread
    count (0, the default; on a one-core machine both are one thread and that half cannot fail), and the process's
    count is what it was once the run ends (an application keeps its setting)."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(3)  # not a value either run uses
    try:
        outs = {}
        for n in (1, 0):
            cfg = make_config(short_loop, tmp_path / f"t{n}", max_frames=90, opencv_threads=n)
            run_job(cfg)
            assert cv2.getNumThreads() == 3
            outs[n] = (tmp_path / f"t{n}" / "trajectory.txt").read_text()
        assert outs[1] == outs[0]
    finally:
        cv2.setNumThreads(before)
