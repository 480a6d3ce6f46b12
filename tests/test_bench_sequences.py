"""The bench's ``sequences`` suite: runs with and without the ground cue, online accuracy, wheel errors."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from windowvo.cli import bench as bench_cli
from windowvo.config import config_from_dict
from windowvo.eval.metrics import evaluate
from windowvo.io.sequence import load_native
from windowvo.io.trajectory import read_tum
from windowvo.runtime.job import load_sequence
from windowvo.tools import bench
from windowvo.types import ScaleSource

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _path_length(positions: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(positions[:, :2], axis=0), axis=1).sum())


def _wheel_over_true_distance(seq) -> float:
    odo, gt = seq.odometry, seq.groundtruth
    return odo.distance(float(gt.timestamps[0]), float(gt.timestamps[-1])) / _path_length(gt.positions)


@pytest.mark.slow
def test_bench_case_with_and_without_ground_cue(tmp_path):
    case = next(c for c in bench.synthetic_cases(5.0) if c.name == "loop_wheels-3pct")
    cache, out = tmp_path / "cache", tmp_path / "out"
    row = bench.run_case(case, cache, out)

    # The rendered wheels report 3% too little distance (nothing in the config says so).
    seq = load_native(cache / case.name)
    assert _wheel_over_true_distance(seq) == pytest.approx(0.97, abs=0.005)
    assert row["wheel_scale_error"] == pytest.approx(-0.03)

    # First run: the defaults (ground cue and online calibration); second: neither.
    assert ScaleSource.GROUND_PLANE.value in row["scale"]["scale_sources"]
    assert ScaleSource.WHEELS_CALIBRATED.value in row["scale"]["scale_sources"]
    assert row["scale"]["wheel_calibration"] is not None
    nc = row["no_ground_cue"]
    assert nc["scale"]["scale_sources"] == [ScaleSource.WHEELS.value]
    assert nc["scale"]["wheel_calibration"] is None
    assert nc["frames"] == row["frames"]

    # Each accuracy in the row is that of the file it names, scored against ground truth here.
    gt = seq.groundtruth
    run_dir = out / case.name
    for acc, traj in ((row["windowvo"], run_dir / "trajectory.txt"),
                      (row["windowvo_online"], run_dir / "trajectory_online.txt"),
                      (nc["windowvo"], run_dir / "no_ground_cue" / "trajectory.txt"),
                      (nc["windowvo_online"], run_dir / "no_ground_cue" / "trajectory_online.txt")):
        assert acc["ate_se3_m"] == pytest.approx(evaluate(gt, read_tum(traj)).ate_se3_rmse_m, rel=1e-3, abs=1e-5)
    assert row["windowvo"]["ate_se3_m"] != nc["windowvo"]["ate_se3_m"]
    assert (run_dir / "trajectories.png").is_file()
    assert row["backend_ms_median"] > 0 and nc["backend_ms_median"] > 0
    # The KITTI relative error of windowvo's smoothed trajectory, recomputed from its file.
    from windowvo.eval.kitti_metric import SegmentSet, kitti_odometry_error

    for s in SegmentSet:
        expected = kitti_odometry_error(gt, read_tum(run_dir / "trajectory.txt"), s)
        got = row["windowvo"]["kitti"][s.value]
        assert got["n_segments"] == expected.n_segments
        assert got["gt_path_length_m"] == pytest.approx(expected.gt_path_length_m, rel=1e-6)


def _row(name: str, kind: str, err: float) -> dict:
    acc = {"ate_se3_m": 0.111, "ate_sim3_m": 0.05, "rpe_m_per_m": 0.02, "end_drift_pct": 1.5}
    return {
        "sequence": name, "kind": kind, "wheel_scale_error": err, "frames": 100, "fps": 50.0,
        "frontend_ms_mean": 4.0, "backend_ms_median": 12.0, "backend_ms_p95": 20.0, "peak_rss_mb": 200.0,
        "windowvo": acc, "windowvo_online": {**acc, "ate_se3_m": 0.222},
        "scale": {"wheel_calibration": {"scale": 0.975}},
        "no_ground_cue": {"backend_ms_median": 10.0, "windowvo": {**acc, "ate_se3_m": 0.333}},
        "backend_cue_cost_pct": 20.0,
        "wheel": {**acc, "ate_se3_m": 0.444}, "chaining": {**acc, "ate_se3_m": 0.555}, "chaining_fps": 30.0,
    }


def test_sequences_table_columns():
    rows = [_row("loop_wheels-3pct", "synth", -0.03), _row("kitti06_000-050_wheels+2pct", "kitti", 0.02)]
    lines = bench.sequences_table(rows).splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    assert len(lines) == 2 + 3 * len(rows)
    cells = [dict(zip(header, (c.strip() for c in ln.strip("|").split("|")), strict=True)) for ln in lines[2:]]
    vo, wheel, chain = cells[0], cells[1], cells[2]
    assert (vo["method"], wheel["method"], chain["method"]) == ("windowvo", "wheel odometry", "E-matrix chaining")
    assert vo["ATE SE(3) m"] == "0.111"
    assert vo["online (causal) ATE SE(3) m"] == "0.222"
    assert vo["ATE SE(3) without ground cue m"] == "0.333"
    assert vo["back-end ms/kf (median / p95)"] == "12.0 / 20.0"
    assert vo["back-end ms/kf median without ground cue (cue cost)"] == "10.0 (+20%)"
    assert vo["wheel scale error: true / estimated"] == "-3.0% / -2.5%"
    assert wheel["ATE SE(3) m"] == "0.444" and chain["ATE SE(3) m"] == "0.555"
    # The baselines have no online or no-cue variant: those cells are blank.
    assert wheel["online (causal) ATE SE(3) m"] == "" and chain["ATE SE(3) without ground cue m"] == ""
    caption = bench.sequences_caption(rows)
    assert "rendered wheels with a -3% scale error: loop_wheels-3pct" in caption
    assert "+2% scale error: kitti06_000-050_wheels+2pct" in caption


def test_sequences_table_monocular_row():
    """A run without wheels: no wheel or chaining baseline (blank), "no wheels" for the scale error, named in
    the caption; the run without the cue is up to scale (its SE(3) ATE blank)."""
    mono = {**_row("kitti01_000-050_monocular", "kitti", 0.0), "wheel_scale_error": None, "wheel": {},
            "chaining": {}, "chaining_fps": float("nan"), "scale": {"wheel_calibration": None},
            "no_ground_cue": {"backend_ms_median": 10.0, "windowvo": {"ate_se3_m": float("nan"), "ate_sim3_m": 0.3}}}
    rows = [_row("loop", "synth", 0.01), mono]
    lines = bench.sequences_table(rows).splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    cells = [dict(zip(header, (c.strip() for c in ln.strip("|").split("|")), strict=True)) for ln in lines[5:]]
    vo, wheel, chain = cells
    assert vo["wheel scale error: true / estimated"] == "no wheels" and vo["ATE SE(3) m"] == "0.111"
    assert vo["ATE SE(3) without ground cue m"] == ""
    assert wheel["ATE SE(3) m"] == "" and chain["ATE SE(3) m"] == "" and chain["fps"] == ""
    caption = bench.sequences_caption(rows)
    assert "no wheels (monocular, the floor at the camera height is the only scale source): " \
           "kitti01_000-050_monocular" in caption
    assert "rendered wheels with a +1% scale error: loop" in caption


def test_bench_rendered_cases_include_unknown_wheel_scale_errors():
    errors = {c.name: c.wheel_scale_error for c in bench.synthetic_cases(30.0)}
    assert errors["loop_wheels+2pct"] == pytest.approx(0.02)
    assert errors["loop_wheels-3pct"] == pytest.approx(-0.03)
    assert {"loop", "figure_eight_vibration", "ramp", "stop_and_go", "wheel_slip"} <= set(errors)


@pytest.mark.skipif(not (SHARED_DATA / "kitti06_000-050").is_dir(), reason="KITTI excerpts not in ../shared/data")
def test_bench_kitti_cases_synthetic_wheels(tmp_path):
    cases = [c for c in bench.kitti_cases() if c.path == SHARED_DATA / "kitti06_000-050"]
    assert [c.name for c in cases] == ["kitti06_000-050", "kitti06_000-050_wheels+2pct", "kitti06_000-050_monocular"]
    for case, expected in zip(cases[:2], (1.01, 1.02), strict=True):
        seq = load_sequence(config_from_dict(bench.case_config_data(case, tmp_path, tmp_path)))
        assert seq.odometry is not None and seq.odometry.synthetic
        ratio = _wheel_over_true_distance(seq)
        assert math.isclose(ratio, expected, abs_tol=0.005), (case.name, ratio)
    mono = load_sequence(config_from_dict(bench.case_config_data(cases[2], tmp_path, tmp_path)))
    assert mono.odometry is None and cases[2].wheel_scale_error is None


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs Linux /proc")
def test_bench_peak_rss_is_the_worker_own():
    # A worker started by a process that once held 300 MB reports its own (small) peak.
    import subprocess
    import sys

    block = bytearray(300 * 2**20)
    block[:: 4096] = b"\x01" * len(block[:: 4096])
    code = "from windowvo.tools.bench import peak_rss_mb; print(peak_rss_mb())"
    peak = float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    del block
    assert 5.0 < peak < 150.0


@pytest.mark.slow
def test_bench_overrides_reach_every_run_and_bad_ones_stop_early(tmp_path, capsys):
    case = next(c for c in bench.synthetic_cases(5.0) if c.name == "loop")
    data = bench.case_config_data(case, tmp_path / "cache", tmp_path / "out",
                                  overrides=("backend.marginalize_every=2", "backend.window_keyframes=9"))
    cfg = config_from_dict(data)
    assert (cfg.backend.marginalize_every, cfg.backend.window_keyframes) == (2, 9)
    assert cfg.run_mode.value == "sequential" and Path(cfg.output) == tmp_path / "out" / "loop"
    # a bad override: one line on stderr and exit 2, before any sequence is rendered or run
    rc = bench_cli.main(["--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--only", "loop",
                     "--set", "backend.marginalize_every=0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "backend.marginalize_every" in err[0], err
    assert not (tmp_path / "c").exists() and not (tmp_path / "o").exists()


def test_bench_cpu_accounting_counts_threads_and_ended_children():
    """The run-modes suite's "cores busy" adds the CPU of every thread and of the ended back-end
    process: a thread and a child process that each burn 0.3 s of CPU both show up."""
    import subprocess
    import threading

    from windowvo.tools.bench import cpu_with_children_s

    burn = "import time\nt = time.thread_time()\nwhile time.thread_time() - t < 0.3: pass\n"
    before = cpu_with_children_s()
    th = threading.Thread(target=exec, args=(burn,))
    th.start()
    th.join()
    after_thread = cpu_with_children_s()
    subprocess.run([sys.executable, "-c", burn], check=True)
    after_child = cpu_with_children_s()
    assert after_thread - before >= 0.29
    assert after_child - after_thread >= 0.29


def _straight(length_m: float, n: int, scale: float = 1.0):
    """A straight drive along x over ``length_m`` in ``n`` poses at 10 Hz, positions times ``scale``."""
    from windowvo.io.trajectory import Trajectory

    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 0, 3] = scale * np.linspace(0.0, length_m, n)
    return Trajectory(np.arange(n) * 0.1, T)


def _cells(table: str) -> list[dict[str, str]]:
    lines = table.splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    return [dict(zip(header, (c.strip() for c in ln.strip("|").split("|")), strict=True)) for ln in lines[2:]]


def test_sequences_table_kitti_columns():
    """t_rel / r_rel over 10-80 m: an estimate 2% too long on a straight drive has no rotation error and a
    t_rel of 2 % of each segment's driven length over its nominal length L (by hand: a segment ends at the
    first pose more than L along, so it is L to L + 0.1 m long at 0.1 m spacing: 2.00-2.02 % for L = 10 m);
    the devkit's 100-800 m columns appear only once some path is longer than 100 m, n/a for the others."""
    from windowvo.tools.kitti_columns import kitti_errors

    short = _row("loop", "synth", 0.01)
    short["windowvo"] = {**short["windowvo"], "kitti": kitti_errors(_straight(50.0, 501), _straight(50.0, 501, 1.02))}
    cells = _cells(bench.sequences_table([short]))
    assert 2.0 <= float(cells[0]["t_rel % (10-80 m)"]) <= 2.0 * 10.1 / 10.0
    assert cells[0]["r_rel deg/100 m (10-80 m)"] == "0.000"
    assert "t_rel % (100-800 m)" not in cells[0]
    assert cells[1]["t_rel % (10-80 m)"] == ""  # the wheel row has no KITTI numbers in this row

    long = _row("kitti06", "kitti", 0.01)
    long["windowvo"] = {**long["windowvo"], "kitti": kitti_errors(_straight(250.0, 2501), _straight(250.0, 2501, 0.97))}
    cells = _cells(bench.sequences_table([short, long]))
    assert cells[0]["t_rel % (100-800 m)"] == "n/a" and cells[0]["r_rel deg/100 m (100-800 m)"] == "n/a"
    # 3% too short, segments of 100-100.1 m (and 200-200.1 m): 3.00 % to two decimals
    assert cells[3]["t_rel % (100-800 m)"] == "3.00" and cells[3]["r_rel deg/100 m (100-800 m)"] == "0.000"
    assert "t_rel / r_rel: the KITTI odometry metric" in bench.sequences_caption([short, long])


def test_missing_kitti_excerpts_are_said_not_silently_dropped(tmp_path, monkeypatch):
    """A suite with KITTI rows run where ``../shared/data`` is not beside the checkout (a git worktree) says so in one
    note; with both excerpts there, or with suites that have no KITTI rows, it says nothing."""
    from windowvo.tools import bench as tools_bench

    monkeypatch.setattr(tools_bench, "SHARED_DATA", tmp_path / "nowhere")
    note = bench_cli.missing_kitti_note(["scale"])
    assert note is not None and "kitti06_000-050" in note and "left out" in note
    assert bench_cli.missing_kitti_note(["frontend", "backend"]) is None
    for name in tools_bench.KITTI_EXCERPTS:
        (tmp_path / "data" / name).mkdir(parents=True)
    monkeypatch.setattr(tools_bench, "SHARED_DATA", tmp_path / "data")
    assert bench_cli.missing_kitti_note(["sequences", "speed"]) is None
