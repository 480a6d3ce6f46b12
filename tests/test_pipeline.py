"""End-to-end regression on rendered sequences: front end + back end against ground truth."""

import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from conftest import make_config

from windowvo.io.trajectory import read_tum
from windowvo.runtime.job import run_job
from windowvo.synth.paths import PathKind

CASES = {
    "loop": dict(path=PathKind.LOOP, duration_s=30.0, seed=21),
    "figure_eight_vibration": dict(path=PathKind.FIGURE_EIGHT, duration_s=30.0, seed=22, vibration_deg=1.5),
    "ramp": dict(path=PathKind.RAMP, duration_s=30.0, seed=23),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_vo_beats_wheel_odometry(seq_factory, tmp_path, name):
    seq = seq_factory(name, **CASES[name])
    rep = run_job(make_config(seq, tmp_path / "out"))
    r = rep.result
    traj = read_tum(tmp_path / "out" / "trajectory.txt")
    assert len(traj) == r.n_frames == len(rep.sequence)  # one line per input frame
    assert rep.accuracy.path_length_m > 20.0
    assert r.n_resets == 0
    # metric: ATE after SE(3) alignment at most a third of the wheel-only ATE
    assert rep.accuracy.ate_se3_rmse_m <= rep.wheel_accuracy.ate_se3_rmse_m / 3.0, (rep.accuracy, rep.wheel_accuracy)
    assert rep.accuracy.ate_se3_rmse_m < 0.1
    stats = (tmp_path / "out" / "stats.csv").read_text().splitlines()
    assert len(stats) == r.n_frames + 1
    assert (tmp_path / "out" / "config_resolved.yaml").is_file()


@pytest.mark.slow
def test_planar_prior_does_not_bend_the_ramp(seq_factory, tmp_path):
    seq = seq_factory("ramp", **CASES["ramp"])
    on = run_job(make_config(seq, tmp_path / "on", max_frames=300))
    off = run_job(make_config(seq, tmp_path / "off", max_frames=300, backend={"planar_prior": {"enabled": False}}))
    assert on.accuracy.ate_se3_rmse_m <= 1.2 * off.accuracy.ate_se3_rmse_m + 0.005
    # the estimate climbs the ramp like the ground truth (0.6 m)
    z = on.result.trajectory.positions[:, 2]
    assert z.max() > 0.45


def test_monocular_run_is_up_to_scale(short_loop, tmp_path, capsys):
    # no wheels and no ground cue: nothing fixes the scale (with the cue, see test_metric_scale.py)
    cfg = make_config(short_loop, tmp_path / "out", backend={"use_odometry": False, "ground": {"enabled": False}})
    rep = run_job(cfg)
    assert rep.result.monocular
    assert "up to scale" in (tmp_path / "out" / "trajectory.txt").read_text().splitlines()[1]
    # shape is right after a similarity alignment
    assert rep.accuracy.ate_sim3_rmse_m < 0.05 * rep.accuracy.path_length_m
    # RPE and end drift are measured in the Sim(3) scale, never in the unit-baseline scale
    assert rep.accuracy.monocular
    assert "after Sim(3) scale" in rep.accuracy.summary(metric=False)
    assert rep.accuracy.as_dict()["ate_se3_rmse_m"] is None


def _with_dropped_frames(src: Path, dst: Path, drop: range) -> int:
    """A native sequence like ``src`` (images linked, not copied) without the frames in ``drop``.

    The data provider logs the timestamp gap when it reaches the next frame, which happens inside
    the pipeline's frame loop: a line on stderr that proves the run is processing frames.
    Returns the number of frames kept.
    """
    (dst / "images").mkdir(parents=True)
    images = sorted((src / "images").iterdir())
    times = [ln for ln in (src / "times.txt").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert len(times) == len(images)
    keep = [i for i in range(len(images)) if i not in drop]
    for i in keep:
        (dst / "images" / images[i].name).symlink_to(images[i])
    (dst / "times.txt").write_text("\n".join(times[i] for i in keep) + "\n")
    for name in ("camera.yaml", "odometry.csv", "groundtruth.txt"):
        if (src / name).is_file():
            (dst / name).symlink_to(src / name)
    return len(keep)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_interruption_keeps_results(seq_factory, tmp_path, sig):
    """Signal a run in its frame loop: exit 130, no traceback, every processed frame written.

    Deterministic: the signal is sent only after the run logged the timestamp gap before frame 12
    (so it is inside the frame loop, with its handlers installed), and about 580 frames are still
    to come then, seconds of work, so the run cannot finish first.
    """
    seq = tmp_path / "seq"
    n_frames = _with_dropped_frames(seq_factory("loop", **CASES["loop"]), seq, range(8, 12))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"sequence: {seq}\noutput: {tmp_path / 'out'}\nprogress: false\nviz:\n  image_every: 1\n")
    stdout = (tmp_path / "stdout.txt").open("w")
    p = subprocess.Popen([sys.executable, "-m", "windowvo.run", str(cfg)], stdout=stdout, stderr=subprocess.PIPE,
                         text=True)
    lines: list[str] = []
    in_loop = threading.Event()

    def pump() -> None:
        assert p.stderr is not None
        for line in p.stderr:
            lines.append(line)
            if "timestamp gap" in line:
                in_loop.set()

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        assert in_loop.wait(timeout=300), "no timestamp-gap line on stderr:\n" + "".join(lines)
        p.send_signal(sig)
        p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
        reader.join(timeout=30)
        stdout.close()
    err = "".join(lines)
    assert p.returncode == 128 + sig, err  # 130 for SIGINT, 143 for SIGTERM
    assert "Traceback" not in err
    assert "interrupted after frame" in err
    assert "[interrupted]" in (tmp_path / "stdout.txt").read_text()
    out = tmp_path / "out"
    traj = read_tum(out / "trajectory.txt")
    rows = (out / "stats.csv").read_text().splitlines()
    assert 8 < len(traj) == len(rows) - 1 < n_frames  # stopped in the loop, after the gap
    # the recording is valid and holds every processed frame
    from rerun.chunk import RrdReader

    images = sum(ch.num_rows for ch in RrdReader(str(out / "recording.rrd")).stream()
                 if str(ch.entity_path) == "/world/estimate/base/cam/image")
    assert images == len(traj)


def test_a_bad_override_of_the_embedded_default_is_one_line_before_any_rendering(tmp_path):
    """The embedded default renders its sequence first (about a minute, once): a bad key or value is told before."""
    r = subprocess.run([sys.executable, "-m", "windowvo.run", "--no-progress", "backend.window_sizee=5"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().startswith("windowvo: error: invalid config") and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "windowvo_output" / "default_sequence").exists()  # nothing rendered


@pytest.mark.slow
def test_default_run_from_the_command_line(tmp_path):
    """The README's main command, in a fresh folder (renders the embedded default sequence)."""
    r = subprocess.run([sys.executable, "-m", "windowvo.run", "--no-progress", "viz.rerun=off"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "ATE SE(3)" in r.stdout
    out = tmp_path / "windowvo_output" / "default"
    traj = read_tum(out / "trajectory.txt")
    n_images = len(list((tmp_path / "windowvo_output" / "default_sequence" / "images").iterdir()))
    assert len(traj) == n_images
