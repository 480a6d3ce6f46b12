"""``scripts/road_region_pose_study.py``: a run's region steps measured at ground truth's poses and at the run's (a
study tool)."""

from __future__ import annotations

import numpy as np
from conftest import load_script


def _script():
    return load_script("road_region_pose_study")


def test_bad_input_is_one_line_and_exit_2(tmp_path, short_loop, capsys):
    mod = _script()
    assert mod.main([str(tmp_path / "none"), str(tmp_path)]) == 2
    assert mod.main([str(short_loop), str(tmp_path)]) == 2  # no run in it
    assert mod.main([str(short_loop), str(tmp_path), "--set", "no_such_key=1"]) == 2
    assert mod.main([str(short_loop), str(tmp_path), "--set", "far_heights"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("road_region_pose_study.py: error:") for line in err), err


def _rows(table: str) -> dict[str, list[str]]:
    return {cells[0]: cells[1:] for line in table.splitlines() if line.startswith("| ")
            for cells in [[c.strip() for c in line.strip("|").split("|")]]}


def test_a_run_at_ground_truths_poses_measures_as_ground_truth(tmp_path, short_loop, capsys):
    """A "run" whose estimate is ground truth itself (every fourth frame a keyframe): each row measures the same steps
    at the same poses, so the estimate's rows repeat ground truth's to the digit, and the floor's steps come out
    within 0.2% (median) of their true lengths (-0.01% when written, 14 steps)."""
    gt = np.loadtxt(short_loop / "groundtruth.txt", comments="#", ndmin=2)
    run = tmp_path / "run"
    run.mkdir()
    for name in ("trajectory_online.txt", "trajectory.txt"):
        (run / name).write_text((short_loop / "groundtruth.txt").read_text())
    lines = ["frame_index,timestamp,is_keyframe"] + [f"{i},{t:.6f},{i % 4 == 0}" for i, t in enumerate(gt[:60, 0])]
    (run / "stats.csv").write_text("\n".join(lines) + "\n")
    mod = _script()
    assert mod.main([str(short_loop), str(run)]) == 0
    rows = _rows(capsys.readouterr().out)
    truth = rows["ground truth"]
    assert int(truth[0]) >= 8, rows
    for mode in ("estimate", "estimate, rotation from truth", "estimate, direction from truth"):
        assert rows[mode] == truth, (mode, rows)
    assert abs(float(truth[1].rstrip("%"))) < 0.2, rows
