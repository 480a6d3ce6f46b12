"""Batch evaluation (``windowvo.batch``) and the executors it shares with the benchmark.

Three short rendered sequences plus one broken copy x two configs, run with the local executor
and with a local Ray instance: the same table from both, the broken sequence failed with its
reason, every run's accuracy recomputed from its own trajectory against ground truth, and a
second invocation that reuses every finished run.
"""

from __future__ import annotations

import ctypes
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from windowvo.cli import batch as batch_cli
from windowvo.errors import ConfigError
from windowvo.eval.metrics import evaluate
from windowvo.io.trajectory import read_tum
from windowvo.synth.generate import SynthSpec, generate_sequence
from windowvo.synth.paths import PathKind
from windowvo.tools import batch
from windowvo.tools.executors import (
    TERM_GRACE_S,
    ExecutorKind,
    ExecutorUnavailableError,
    LocalExecutor,
    Task,
    TaskStatus,
    call_task,
    make_executor,
)

MAX_FEATURES = [120, 200]
MAX_FRAMES = 60
N_TIMES_BROKEN = 20


@pytest.fixture(scope="module")
def batch_dir(tmp_path_factory) -> Path:
    """seqs/{loop,fig8,ramp} rendered (3.5 s each), seqs/broken (times.txt too short), a base config."""
    root = tmp_path_factory.mktemp("batch")
    seqs = root / "seqs"
    for name, kind, seed in (("loop", PathKind.LOOP, 71), ("fig8", PathKind.FIGURE_EIGHT, 72),
                             ("ramp", PathKind.RAMP, 73)):
        generate_sequence(seqs / name, SynthSpec(path=kind, duration_s=3.5, seed=seed))
    broken = seqs / "broken"
    broken.mkdir()
    (broken / "images").symlink_to(seqs / "loop" / "images", target_is_directory=True)
    (broken / "camera.yaml").write_text((seqs / "loop" / "camera.yaml").read_text())
    times = (seqs / "loop" / "times.txt").read_text().splitlines()
    (broken / "times.txt").write_text("\n".join(times[:N_TIMES_BROKEN]) + "\n")
    (root / "base.yaml").write_text(f"max_frames: {MAX_FRAMES}\nbackend:\n  window_keyframes: 15\n")
    return root


def write_spec(root: Path, output: str, grid: list[int] = MAX_FEATURES) -> Path:
    spec = {
        "sequences": [
            {"path": "seqs/[bfl]*"},  # glob: broken, fig8, loop
            {"path": "seqs/ramp", "dataset": "native", "overrides": {"keyframes.max_interval_s": 0.8}},
        ],
        "base": "base.yaml",
        "grid": {"frontend.max_features": grid},
        "output": output,
        "timeout_s": 300,
    }
    path = root / f"spec_{output}.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def local_batch(batch_dir):
    spec = write_spec(batch_dir, "out_local")
    return spec, batch.run_batch(spec, ExecutorKind.LOCAL, jobs=2, progress=False)


def _table(result: batch.BatchResult) -> dict[str, dict]:
    return {r.run_id: {"status": r.status, "reason": r.reason, "frames": r.frames, "keyframes": r.keyframes,
                       "ate_se3_m": r.ate_se3_m, "ate_sim3_m": r.ate_sim3_m, "grid": r.grid_values}
            for r in result.rows}


def _assert_same_table(a: dict[str, dict], b: dict[str, dict]) -> None:
    assert a.keys() == b.keys()
    for run_id in a:
        ra, rb = a[run_id], b[run_id]
        for k in ("status", "reason", "frames", "keyframes", "grid"):
            assert ra[k] == rb[k], (run_id, k)
        for k in ("ate_se3_m", "ate_sim3_m"):
            if ra[k] is None:
                assert rb[k] is None, (run_id, k)
            else:
                assert rb[k] == pytest.approx(ra[k], abs=1e-9), (run_id, k)


@pytest.mark.slow
def test_local_batch_results_against_ground_truth(local_batch, batch_dir):
    spec, result = local_batch
    seqs = ["broken", "fig8", "loop", "ramp"]
    assert [r.run_id for r in result.rows] == [f"c{i:02d}/{s}" for i in range(2) for s in seqs]
    assert result.n_ran == 8 and result.n_reused == 0
    for r in result.rows:
        run_dir = result.out_root / "runs" / r.run_id
        assert r.grid_values == {"frontend.max_features": MAX_FEATURES[int(r.config_id[1:])]}
        if r.sequence == "broken":
            assert r.status is TaskStatus.FAILED
            n_images = len(list((batch_dir / "seqs" / "loop" / "images").iterdir()))
            assert r.reason == f"times.txt has {N_TIMES_BROKEN} timestamps but images/ has {n_images} frames"
            continue
        assert r.status is TaskStatus.OK, r.reason
        # The run used the grid value, the base config, the per-sequence override and no recording.
        ran = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
        assert ran["frontend"]["max_features"] == r.grid_values["frontend.max_features"]
        assert ran["max_frames"] == MAX_FRAMES and ran["backend"]["window_keyframes"] == 15
        assert ran["viz"]["rerun"] == "off"
        assert ran["keyframes"]["max_interval_s"] == (0.8 if r.sequence == "ramp" else 1.0)
        assert not (run_dir / "recording.rrd").exists()
        assert r.frames == MAX_FRAMES
        # The table's ATE is the run's own trajectory against the rendered ground truth.
        gt = read_tum(batch_dir / "seqs" / r.sequence / "groundtruth.txt")
        acc = evaluate(gt, read_tum(run_dir / "trajectory.txt"))
        assert r.ate_se3_m == pytest.approx(acc.ate_se3_rmse_m, abs=2e-5)
        assert r.ate_sim3_m == pytest.approx(acc.ate_sim3_rmse_m, abs=2e-5)
        assert r.ate_se3_m < 0.1  # 3 s of rendered motion with wheel odometry: centimetres
        assert json.loads((run_dir / batch.RUN_MARKER).read_text())["config_hash"] == \
            batch.plan_runs(batch.load_spec(spec), spec.parent)[result.rows.index(r)].config_hash
    # results.csv holds the same numbers at full precision.
    csv_rows = {row["run_id"]: row for row in batch.read_results_csv(result.files["csv"])}
    for r in result.rows:
        row = csv_rows[r.run_id]
        assert row["status"] == r.status.value and row["reason"] == r.reason
        assert row["frontend.max_features"] == str(r.grid_values["frontend.max_features"])
        if r.ate_se3_m is not None:
            assert float(row["ate_se3_m"]) == r.ate_se3_m
            assert float(row["ate_sim3_m"]) == r.ate_sim3_m
            assert int(row["keyframes"]) == r.keyframes
    # The report's best config for ATE SE(3) is the lowest mean over the sequences both configs finished.
    means = {c: sum(r.ate_se3_m for r in result.rows if r.config_id == c and r.ate_se3_m is not None) / 3
             for c in ("c00", "c01")}
    best = min(means, key=lambda c: means[c])
    report = result.files["report"].read_text()
    assert f"| ATE SE(3) m | {best} | {means[best]:.3f} |" in report
    assert "| c00/broken | times.txt has" in report and "| c01/broken | times.txt has" in report
    assert "| c00 | 3 / 4 |" in report
    assert result.files["plot"].stat().st_size > 10_000


@pytest.mark.slow
def test_second_invocation_reuses_finished_runs(local_batch):
    spec, first = local_batch
    finished = [r for r in first.rows if r.status is TaskStatus.OK]
    mtimes = {r.run_id: (first.out_root / "runs" / r.run_id / "summary.json").stat().st_mtime_ns for r in finished}
    again = batch.run_batch(spec, ExecutorKind.LOCAL, jobs=2, progress=False)
    assert again.n_reused == len(finished) == 6
    assert again.n_ran == 2  # only the broken sequence is tried again, and fails again
    assert all(r.reused for r in again.rows if r.status is TaskStatus.OK)
    for run_id, mtime in mtimes.items():
        assert (again.out_root / "runs" / run_id / "summary.json").stat().st_mtime_ns == mtime
    _assert_same_table(_table(first), _table(again))


@pytest.mark.slow  # its fixture runs the local batch
def test_changed_config_is_not_reused(local_batch, batch_dir):
    """Planning only: a run folder with another config's summary does not count as finished."""
    _, result = local_batch
    assert any(r.status is TaskStatus.OK for r in result.rows)
    spec = batch.load_spec(write_spec(batch_dir, "out_local", grid=[120, 300]))
    plans = {p.run_id: p for p in batch.plan_runs(spec, batch_dir)}
    assert batch.finished_summary(plans["c00/loop"]) is not None  # 120 as before
    assert batch.finished_summary(plans["c01/loop"]) is None  # 300 where 200 ran
    assert batch.finished_summary(plans["c00/broken"]) is None  # failed runs are never finished


@pytest.mark.slow
def test_ray_batch_gives_the_same_table(local_batch, batch_dir):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'windowvo[cluster]')")
    _, local = local_batch
    spec = write_spec(batch_dir, "out_ray")
    result = batch.run_batch(spec, ExecutorKind.RAY, jobs=2, progress=False)
    assert result.executor == "ray" and result.n_ran == 8
    _assert_same_table(_table(local), _table(result))
    again = batch.run_batch(spec, ExecutorKind.RAY, jobs=2, progress=False)
    assert again.n_reused == 6 and again.n_ran == 2


# ---------------------------------------------------------------------------- bad specs


@pytest.mark.parametrize(
    "text,needle",
    [
        ("sequences: [a]\noutput: o\nthreads: 4\n", "'threads': unknown key"),
        ("sequences: [a]\n", "'output': required key is missing"),
        ("sequences: [a]\noutput: o\ngrid:\n  frontend.max_features: 200\n", "'grid.frontend.max_features'"),
        ("sequences: [a]\noutput: o\ntimeout_s: -3\n", "'timeout_s'"),
        ("sequences:\n  - path: a\n    dataset: lidar\noutput: o\n", "'sequences.0.dataset'"),
        ("sequences: []\noutput: o\n", "'sequences'"),
        ("sequences: [a]\noutput: o\ngrid:\n  output: [x, y]\n", "cannot be varied"),
        ("sequences: [a]\noutput: o\ngrid:\n  frontend.max_feature: [1]\n", "'frontend.max_feature': unknown key"),
        ("sequences: [a]\noutput: o\ngrid:\n  frontend.max_features: [lots]\n", "'frontend.max_features'"),
        ("sequences: [nothing*]\noutput: o\n", "matches no folder"),
        ("sequences: [a]\noutput: o\nbase: missing.yaml\n", "base config not found"),
        ("sequences: [a, b/a]\noutput: o\n", "two sequences are named 'a'"),
        ("sequences: [unclosed\n", "not valid YAML"),
    ],
)
def test_bad_spec_is_one_line_and_exit_2(tmp_path, capsys, text, needle):
    spec = tmp_path / "spec.yaml"
    spec.write_text(text)
    assert batch_cli.main([str(spec), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("windowvo: error: ") and needle in err, err
    assert "\n" not in err
    assert not (tmp_path / "o").exists()  # nothing ran


def test_bad_spec_from_the_command_line(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("sequences: [a]\noutput: o\ngrid: [1, 2]\n")
    proc = subprocess.run([sys.executable, "-m", "windowvo.batch", str(spec)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
    assert proc.stderr.startswith("windowvo: error: invalid batch spec") and "'grid'" in proc.stderr


def test_ray_missing_is_one_line(tmp_path, capsys, monkeypatch):
    (tmp_path / "a").mkdir()
    spec = tmp_path / "spec.yaml"
    spec.write_text("sequences: [a]\noutput: o\n")
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError, as without the extra
    assert batch_cli.main([str(spec), "--executor", "ray", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == 'windowvo: error: the ray executor needs Ray: pip install "windowvo[cluster]"'
    with pytest.raises(ExecutorUnavailableError):
        make_executor(ExecutorKind.LOCAL, 1, address="ray://head:10001")


def test_merge_config_nested_and_dotted():
    data = {"frontend": {"max_features": 200, "clahe": True}, "max_frames": 10}
    batch.merge_config(data, {"frontend.max_features": 300, "backend": {"odometry": {"robust": "huber"}}})
    batch.merge_config(data, {"backend.odometry.robust_k": 2.0})
    assert data == {"frontend": {"max_features": 300, "clahe": True}, "max_frames": 10,
                    "backend": {"odometry": {"robust": "huber", "robust_k": 2.0}}}
    with pytest.raises(ConfigError, match="not a section"):
        batch.merge_config(data, {"max_frames.x": 1})
    assert batch.grid_combinations({"a": [1, 2], "b": ["x", "y", "z"]})[4] == {"a": 2, "b": "y"}
    assert len(batch.grid_combinations({})) == 1


# ---------------------------------------------------------------------------- executors


def test_local_executor_isolates_crashes_timeouts_and_errors():
    tasks = [
        call_task("segfault", ctypes.string_at, 0),  # a native crash (SIGSEGV) in the worker
        call_task("sleep", time.sleep, 60, timeout_s=1.0),
        call_task("value", math.hypot, 3.0, 4.0),
        call_task("windowvo_error", read_tum, "/nonexistent/traj.txt"),
        Task("exit", ("-c", "import sys; sys.exit('plain failure')")),
        Task("run_cli", ("-m", "windowvo.run", "/nonexistent/config.yaml", "--no-progress", "-q")),
    ]
    t0 = time.perf_counter()
    out = {o.key: o for o in LocalExecutor(jobs=2).run(tasks)}
    assert time.perf_counter() - t0 < 30  # the sleeper was stopped at its time-out, not after 60 s
    assert out["segfault"].status is TaskStatus.FAILED and out["segfault"].reason == "killed by SIGSEGV"
    assert out["sleep"].reason == "timed out after 1 s"
    assert out["value"].ok and out["value"].value == 5.0
    assert out["windowvo_error"].reason == "trajectory file not found: /nonexistent/traj.txt" and out["windowvo_error"].returncode == 2
    assert out["exit"].reason == "exit code 1: plain failure"
    assert out["run_cli"].reason == "config file not found: /nonexistent/config.yaml"


def _probe(folder: Path, module: str, source: str) -> str:
    """Write ``source`` as ``module``.py into ``folder`` and run it there as ``python -m module``: its stdout."""
    (folder / f"{module}.py").write_text(source)
    proc = subprocess.run([sys.executable, "-m", module], capture_output=True, text=True, timeout=120, cwd=folder)
    return proc.stdout.strip() + ("" if proc.returncode == 0 else f"\n(exit {proc.returncode}) {proc.stderr}")


def test_call_task_resolves_main_module_objects(tmp_path):
    """Functions and classes of a module run as ``python -m`` pickle as ``__main__.X``; the worker maps them back."""
    out = _probe(tmp_path, "batchprobe",
        "from dataclasses import dataclass\n"
        "from windowvo.tools.executors import LocalExecutor, call_task\n"
        "@dataclass\n"
        "class Leg:\n"
        "    a: float\n"
        "    b: float\n"
        "def length(leg):\n"
        "    return (leg.a ** 2 + leg.b ** 2) ** 0.5\n"
        "if __name__ == '__main__':\n"
        "    (o,) = LocalExecutor(1).run([call_task('leg', length, Leg(6.0, 8.0))])\n"
        "    print(o.status.value, o.value, o.reason)\n"
    )
    assert out == "ok 10.0", out


def test_a_stop_signal_ends_the_whole_call_not_only_its_run_in_progress(tmp_path):
    """A call of many runs (a scale-suite case is eight) that gets SIGTERM during a run (its parent stopping it, timing
    it out or dying): that run still writes what it has, and no later run starts; the call ends 143, no value."""
    out = _probe(tmp_path, "stopprobe",
        "import os, signal\n"
        "from pathlib import Path\n"
        "from windowvo.runtime import stop\n"
        "from windowvo.tools.executors import LocalExecutor, call_task\n"
        "def two_runs(folder):\n"
        "    for i in range(2):\n"
        "        with stop.guarded(stop.Phase.RAISE):  # as run_job enters a run\n"
        "            stop.set_phase(stop.Phase.DEFER)  # its frames: a signal stops the run, which writes\n"
        "            if i == 0:\n"
        "                os.kill(os.getpid(), signal.SIGTERM)\n"
        "            Path(folder, f'run{i}').write_text('written')\n"
        "    return 'both'\n"
        "if __name__ == '__main__':\n"
        "    (o,) = LocalExecutor(1).run([call_task('runs', two_runs, os.getcwd())])\n"
        "    print(o.status.value, o.value, o.reason)\n"
    )
    assert out == "failed None stopped by SIGTERM (exit code 143)", out
    assert (tmp_path / "run0").is_file() and not (tmp_path / "run1").exists()


def test_a_call_timed_out_after_a_run_stops_at_its_sigterm(tmp_path):
    """A call whose run is over and which goes on with other work (evaluation, a plot; here a sleep) is stopped by
    its time-out's SIGTERM at once, not by the SIGKILL TERM_GRACE_S later."""
    out = _probe(tmp_path, "sleepprobe",
        "import time\n"
        "from windowvo.runtime import stop\n"
        "from windowvo.tools.executors import LocalExecutor, call_task\n"
        "def run_then_sleep(seconds):\n"
        "    with stop.guarded(stop.Phase.RAISE):  # as run_job enters a run\n"
        "        stop.set_phase(stop.Phase.DEFER)  # its frames\n"
        "    time.sleep(seconds)\n"
        "if __name__ == '__main__':\n"
        "    t0 = time.perf_counter()\n"
        "    (o,) = LocalExecutor(1).run([call_task('sleeper', run_then_sleep, 60.0, timeout_s=2.0)])\n"
        "    print(o.reason, round(time.perf_counter() - t0))\n"
    )
    reason, _, seconds = out.rpartition(" ")
    assert reason == "timed out after 2 s", out
    assert int(seconds) < 2 + TERM_GRACE_S / 2, out  # SIGTERM ended it, not the SIGKILL after the grace


def test_globs_match_folders_and_for_bags_and_videos_files(tmp_path):
    rec = tmp_path / "rec"
    (rec / "day1").mkdir(parents=True)
    (rec / "day2").mkdir()
    (rec / "notes.txt").write_text("not a sequence")
    (rec / "a.mp4").write_bytes(b"")
    (rec / "b.mp4").write_bytes(b"")
    spec_path = tmp_path / "spec.yaml"
    spec_path.write_text("sequences:\n  - rec/*\n  - {path: 'rec/*.mp4', dataset: video}\noutput: out\n"
                         "grid:\n  frontend.max_features: [100, 300]\n")
    plans = batch.plan_runs(batch.load_spec(spec_path), tmp_path)
    assert [p.run_id for p in plans] == ["c00/day1", "c00/day2", "c00/a.mp4", "c00/b.mp4",
                                         "c01/day1", "c01/day2", "c01/a.mp4", "c01/b.mp4"]
    assert [p.resolved["dataset"] for p in plans[:4]] == ["native", "native", "video", "video"]
    assert plans[2].resolved["sequence"] == str(rec / "a.mp4")
    assert plans[4].run_dir == tmp_path / "out" / "runs" / "c01" / "day1"
    # The hash sees the grid value and the sequence, not the output folder.
    assert len({p.config_hash for p in plans}) == 8
    assert batch.config_hash({**plans[0].resolved, "output": "/elsewhere"}) == plans[0].config_hash


def test_online_accuracy_is_reported_when_the_summary_has_it(tmp_path):
    plan = batch.RunPlan("c00/s", "c00", "s", batch.DatasetKind.NATIVE, {"frontend.max_features": 150}, {}, "h",
                         tmp_path)
    base = {"frames": 100, "keyframes": 20, "fps": 50.0, "monocular": False,
            "accuracy": {"ate_se3_rmse_m": 0.05, "ate_sim3_rmse_m": 0.02}}
    without = batch.row_from_summary(plan, base, 3.0, reused=False)
    with_online = batch.row_from_summary(plan, {**base, "accuracy_online": {"ate_se3_rmse_m": 0.08}}, 3.0, False)
    monocular = batch.row_from_summary(plan, {**base, "monocular": True,
                                              "accuracy": {"ate_se3_rmse_m": None, "ate_sim3_rmse_m": 0.03}}, 3.0,
                                       False)
    assert without.ate_online_se3_m is None and with_online.ate_online_se3_m == 0.08
    assert (with_online.ate_se3_m, with_online.ate_sim3_m, with_online.keyframes) == (0.05, 0.02, 20)
    assert monocular.ate_se3_m is None and monocular.ate_sim3_m == 0.03
    batch.write_results_csv(tmp_path / "r.csv", [without, with_online, monocular], ["frontend.max_features"])
    rows = batch.read_results_csv(tmp_path / "r.csv")
    assert [r["ate_online_se3_m"] for r in rows] == ["", "0.08", ""]
    assert [r["ate_se3_m"] for r in rows] == ["0.05", "0.05", ""]


def _straight(length_m: float, n: int, scale: float = 1.0):
    from windowvo.io.trajectory import Trajectory

    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 0, 3] = scale * np.linspace(0.0, length_m, n)
    return Trajectory(np.arange(n) * 0.1, T)


def test_kitti_columns_in_results_csv_and_report(tmp_path):
    """The KITTI relative errors reach results.csv (four columns, blank without a segment) and report.md
    (the devkit's 100-800 m only when some run has such a segment)."""
    from windowvo.tools.kitti_columns import kitti_errors

    plan = batch.RunPlan("c00/s", "c00", "s", batch.DatasetKind.NATIVE, {}, {}, "h", tmp_path)
    summary = {"frames": 100, "keyframes": 20, "fps": 50.0, "accuracy": {"ate_se3_rmse_m": 0.05}}
    # 3% too long on a straight 50 m drive: t_rel 3 % of each segment's driven length (L to L + 0.1 m) over L
    short = batch.row_from_summary(plan, summary, 1.0, False, kitti_errors(_straight(50.0, 501),
                                                                           _straight(50.0, 501, 1.03)))
    assert 3.0 <= short.kitti_short_t_rel_pct <= 3.0 * 10.1 / 10.0
    assert short.kitti_short_r_rel_deg_per_100m == 0.0 and short.kitti_devkit_t_rel_pct is None
    batch.write_results_csv(tmp_path / "r.csv", [short], [])
    row = batch.read_results_csv(tmp_path / "r.csv")[0]
    assert float(row["kitti_short_t_rel_pct"]) == short.kitti_short_t_rel_pct
    assert row["kitti_devkit_t_rel_pct"] == "" and row["kitti_devkit_r_rel_deg_per_100m"] == ""
    result = batch.BatchResult([short], 1.0, 0, 1, tmp_path, "local", 1)
    report = batch.report_markdown(result, [], tmp_path / "spec.yaml")
    assert "t_rel % (10-80 m) mean" in report and "100-800 m" not in report
    assert f"| t_rel % (10-80 m) | c00 | {short.kitti_short_t_rel_pct:.3f} |" in report
    long = batch.row_from_summary(plan, summary, 1.0, False, kitti_errors(_straight(150.0, 1501),
                                                                          _straight(150.0, 1501, 1.03)))
    assert long.kitti_devkit_t_rel_pct == pytest.approx(3.0, abs=0.01)
    report = batch.report_markdown(batch.BatchResult([short, long], 1.0, 0, 2, tmp_path, "local", 1), [],
                                   tmp_path / "spec.yaml")
    assert "t_rel % (100-800 m) mean" in report


@pytest.mark.slow  # its fixture runs the local batch (about 30 s)
def test_batch_runs_carry_their_kitti_error(local_batch, batch_dir):
    """Each finished run's KITTI error is its own smoothed trajectory against the sequence's ground truth,
    kept in batch_run.json (a reused run reads it there)."""
    from windowvo.eval.kitti_metric import SegmentSet, kitti_odometry_error

    _, result = local_batch
    ok = [r for r in result.rows if r.status is TaskStatus.OK]
    assert ok
    for r in ok:
        run_dir = result.out_root / "runs" / r.run_id
        gt = read_tum(batch_dir / "seqs" / r.sequence / "groundtruth.txt")
        for s in SegmentSet:
            expected = kitti_odometry_error(gt, read_tum(run_dir / "trajectory.txt"), s)
            assert r.kitti[s.value]["n_segments"] == expected.n_segments
            assert r.kitti[s.value]["gt_path_length_m"] == pytest.approx(expected.gt_path_length_m, rel=1e-6)
        assert json.loads((run_dir / batch.RUN_MARKER).read_text())["kitti"] == r.kitti
    header = batch.read_results_csv(result.files["csv"])[0].keys()
    assert {"kitti_short_t_rel_pct", "kitti_short_r_rel_deg_per_100m", "kitti_devkit_t_rel_pct"} <= set(header)
