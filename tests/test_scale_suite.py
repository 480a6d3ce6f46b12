"""The scale suite's cases and its summary (the runs themselves are the benchmark's, not a test's)."""

from __future__ import annotations

import math

from conftest import SHARED_DATA

from windowvo.tools import scale_suite as ss


def test_the_suite_has_thirty_sequences_of_every_scene_kind():
    cases = ss.suite_cases()
    kinds = {c.scene for c in cases}
    assert {"room", "warehouse", "street"} <= kinds
    if SHARED_DATA.is_dir():
        assert "kitti" in kinds and len(cases) >= 30
    assert len({c.name for c in cases}) == len(cases)
    # the wheel errors vary what the estimator does not model
    wheels = [c.spec["wheel"] for c in cases if c.scene != "kitti"]
    assert {w["scale_error"] > 0 for w in wheels} == {True, False}
    assert any(w["yaw_scale_error"] != 0 for w in wheels) and any(w["slip_windows"] for w in wheels)
    assert any(c.spec.get("vibration_deg", 0) > 0 for c in cases if c.scene != "kitti")


def test_every_rendered_case_is_a_valid_spec():
    for c in ss.rendered_cases():
        spec = ss.synth_spec(c)
        assert spec.duration_s == ss.DURATION_S and spec.scene.value == c.scene


def _row(name, fused, floor, wheels, alone, sim3=0.01, scene="room"):
    way = lambda se3: {"se3": se3, "sim3": sim3}  # noqa: E731
    return {"sequence": name, "scene": scene, "fused": way(fused), "floor": way(floor), "wheels": way(wheels),
            "none": way(float("nan")), "wheels_alone": way(alone),
            "fused_over_best": fused / min(floor, wheels), "fused_se3_over_sim3": fused / sim3}


def test_the_summary_is_the_distribution_of_fused_over_the_best_cue():
    rows = [_row("a", 0.02, 0.01, 0.04, 0.5), _row("b", 0.01, 0.02, 0.01, 0.005), _row("c", 0.03, 0.03, 0.06, 0.2)]
    s = ss.summary(rows)
    assert math.isclose(s["fused_over_best_gmean"], (2.0 * 1.0 * 1.0) ** (1 / 3))
    assert s["fused_over_best_worst"] == 2.0
    assert math.isclose(s["share_within_1.1x"], 2 / 3)
    assert s["fused_worse_than_wheels_alone"] == 1  # b: 0.01 m against the wheels' 0.005 m
    assert "2.00x" in ss.table(rows) and "3 sequences" in ss.summary_text(s)


def test_overrides_change_every_way_but_not_its_cue_switches(tmp_path, monkeypatch):
    """--set reaches every way of the scale suite; a way's own cue switch (floor only: no wheels) still wins."""
    case = next(c for c in ss.suite_cases() if c.kitti_path is not None) if SHARED_DATA.is_dir() else None
    if case is None:  # a rendered case would render here: build its config without the sequence
        case = ss.rendered_cases()[0]
        monkeypatch.setattr(ss, "ensure_rendered", lambda c, cache: tmp_path / c.name)
    over = ("backend.ground.robust=cauchy", "backend.use_odometry=true", "backend.ground.enabled=true")
    plain = ss.case_config(case, tmp_path, tmp_path, "floor")
    floor = ss.case_config(case, tmp_path, tmp_path, "floor", over)
    wheels = ss.case_config(case, tmp_path, tmp_path, "wheels", over)
    assert "robust" not in plain["backend"].get("ground", {})
    assert floor["backend"]["ground"]["robust"] == "cauchy" and wheels["backend"]["ground"]["robust"] == "cauchy"
    assert floor["backend"]["use_odometry"] is False  # the way's switch, applied after the overrides
    assert wheels["backend"]["ground"]["enabled"] is False


def test_a_seeded_way_runs_in_its_own_folder_with_its_seed(tmp_path, monkeypatch):
    """``--seeds``: a run of a way with the floor's RANSAC seed k writes to ``<way>/seed<k>`` and sets
    ``backend.ground.seed``; the way's own cue switch still applies; no seed: the config's, the folder as before."""
    case = ss.rendered_cases()[0]
    monkeypatch.setattr(ss, "ensure_rendered", lambda c, cache: tmp_path / c.name)
    seeded = ss.case_config(case, tmp_path, tmp_path, "floor", ("backend.ground.robust=cauchy",), seed=2)
    assert seeded["output"] == str(tmp_path / case.name / "floor" / "seed2")
    assert seeded["backend"]["ground"]["seed"] == 2 and seeded["backend"]["ground"]["robust"] == "cauchy"
    assert seeded["backend"]["use_odometry"] is False
    plain = ss.case_config(case, tmp_path, tmp_path, "floor")
    assert plain["output"] == str(tmp_path / case.name / "floor") and "seed" not in plain["backend"].get("ground", {})


def test_the_seeds_runs_give_their_medians_and_spread():
    runs = [{"se3": 0.02, "sim3": 0.010, "metric": True}, {"se3": 0.01, "sim3": 0.012, "metric": True},
            {"se3": 0.04, "sim3": 0.011, "metric": True}]
    way = ss._median_of_runs(runs)
    assert way["se3"] == 0.02 and way["sim3"] == 0.011 and way["se3_runs"] == [0.02, 0.01, 0.04]
    assert way["seed_spread"] == 4.0
    assert ss._median_of_runs(runs[:1]) == runs[0]  # one run: the run itself
    rows = [_row("a", 0.02, 0.01, 0.04, 0.5), _row("b", 0.01, 0.02, 0.01, 0.005)]
    rows[0]["fused"], rows[0]["floor"] = way, {**ss._median_of_runs(runs[:2]), "se3": 0.01}
    rows[1]["fused"], rows[1]["floor"] = ss._median_of_runs(runs[:2]), ss._median_of_runs(runs[1:])
    s = ss.summary(rows)
    assert s["seeds"] == 3
    assert s["fused_seed_spread_within_1.1x"] == 0.0  # 4x and 2x apart
    assert "median over 3 seeds" in ss.summary_text(s)


def test_bad_seeds_are_one_line_and_exit_2(tmp_path, capsys):
    from windowvo.cli.bench import main

    for argv in (["--suite", "scale", "--seeds", "0"], ["--suite", "scale", "--seeds", "2", "--set",
                 "backend.ground.seed=1"], ["--suite", "speed", "--seeds", "3"]):
        assert main([*argv, "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("windowvo.bench: error: --seeds"), err
