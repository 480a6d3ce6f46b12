"""The scale suite's comparison of two results (``python -m windowvo.scale_compare``): the distribution of the ratios
per way and scene, the seeds' spread, and clear errors for what is not a result."""

from __future__ import annotations

import json

import numpy as np
import pytest

from windowvo.cli.scale_compare import main
from windowvo.tools.scale_compare import chance_beyond_each_side, compare, comparison_text


def _row(name: str, scene: str, fused: float, floor: float, runs: list[float] | None = None,
         floor_runs: list[float] | None = None) -> dict:
    def way(se3: float, se3_runs: list[float] | None) -> dict:
        return {"se3": se3, "sim3": se3} | ({"se3_runs": se3_runs} if se3_runs is not None else {})

    return {"sequence": name, "scene": scene, "fused": way(fused, runs), "floor": way(floor, floor_runs),
            "fused_over_best": fused / floor}


def _results(rows: list[dict], gmean: float, worse_than_wheels: int = 0) -> dict:
    summary = {"fused_over_best_gmean": gmean, "fused_worse_than_wheels_alone": worse_than_wheels, "note": "text"}
    return {"rows": rows, "summary": summary}


SEEDS = [0.0, 0.0, 0.0]  # placeholder runs of the "after" side: only their count matters
BEFORE = _results([_row("a", "room", 0.010, 0.020, [0.009, 0.010, 0.012], [0.019, 0.020, 0.021]),
                   _row("b", "room", 0.040, 0.020, [0.030, 0.040, 0.050], [0.019, 0.020, 0.021]),
                   _row("c", "street", 0.100, 0.200, [0.090, 0.100, 0.110], [0.190, 0.200, 0.210]),
                   _row("d", "street", 0.100, 0.200, [0.090, 0.100, 0.110], [0.190, 0.200, 0.210]),
                   _row("gone", "street", 1.0, 1.0)], 0.8, 1)
AFTER = _results([_row("a", "room", 0.020, 0.020, SEEDS, SEEDS),  # twice as bad, beyond the old seeds' runs
                  _row("b", "room", 0.045, 0.020, SEEDS, SEEDS),  # worse, but within the old seeds' spread: chance
                  _row("c", "street", 0.050, 0.100, SEEDS, SEEDS),  # half, beyond the old runs
                  _row("d", "street", 0.050, 0.100, SEEDS, SEEDS),  # the same
                  _row("new", "street", 1.0, 1.0)], 0.7, 0)


def test_the_ratios_are_judged_per_way_and_scene_against_the_old_seeds():
    c = compare(BEFORE, AFTER)
    assert [s.sequence for s in c.sequences] == ["a", "b", "c", "d"]
    assert c.only_before == ["gone"] and c.only_after == ["new"]
    fused, floor = c.ways
    assert fused.way == "fused" and fused.gmean == pytest.approx((2.0 * 1.125 * 0.5 * 0.5) ** (1 / 4))
    assert (fused.worst, fused.worst_sequence) == (pytest.approx(2.0), "a")
    assert (fused.best, fused.best_sequence) == (pytest.approx(0.5), "c")
    assert fused.by_scene == {"room": pytest.approx((2.0 * 1.125) ** 0.5), "street": pytest.approx(0.5)}
    assert fused.beyond_seeds == (2, 1)  # c and d below their old runs, a above
    assert floor.beyond_seeds == (2, 0) and floor.gmean == pytest.approx(0.5 ** 0.5)
    assert c.summary == {"fused_over_best_gmean": (0.8, 0.7), "fused_worse_than_wheels_alone": (1, 0)}
    text = comparison_text(c)
    assert "| a | 0.010 | 0.020 | 2.00x (worse) |" in text and "| c | 0.100 | 0.050 | 0.50x (better) |" in text
    assert "only before: gone" in text and "fused_over_best_gmean: 0.800 -> 0.700" in text
    assert "fused_worse_than_wheels_alone: 1 -> 0" in text and "2 better, 1 worse (chance alone: about 1 each" in text
    assert fused.chance_each_side == pytest.approx(0.2)


def test_the_chance_share_is_the_order_statistics_of_exchangeable_runs():
    rng = np.random.default_rng(3)
    for n_new, n_old in [(3, 3), (5, 3), (1, 4)]:
        runs = rng.normal(size=(40000, n_new + n_old))
        below = np.median(runs[:, :n_new], axis=1) < runs[:, n_new:].min(axis=1)
        assert below.mean() == pytest.approx(chance_beyond_each_side(n_new, n_old), abs=0.01), (n_new, n_old)


def test_runs_without_seeds_or_without_a_finite_ate_are_not_judged():
    before = _results([_row("a", "room", 0.010, 0.020), _row("b", "room", float("nan"), 0.020),
                       _row("c", "room", 0.0, 0.020)], 1.0)
    after = _results([_row("a", "room", 0.030, 0.020), _row("b", "room", 0.010, 0.020),
                      _row("c", "room", 0.010, 0.020)], 1.0)
    fused = compare(before, after).ways[0]
    assert fused.beyond_seeds is None  # --seeds 1: nothing to say, not "0 better, 0 worse"
    assert fused.gmean == pytest.approx(3.0) and (fused.worst, fused.best) == (pytest.approx(3.0), pytest.approx(3.0))
    text = comparison_text(compare(before, after))
    assert "beyond the old seeds' runs: n/a" in text and "| b | n/a | 0.010 | n/a |" in text


def test_the_command_line_reads_a_benchmark_folder_and_refuses_what_is_not_a_result(tmp_path, capsys):
    (tmp_path / "before" / "scale").mkdir(parents=True)
    (tmp_path / "before" / "scale" / "scale_suite.json").write_text(json.dumps(BEFORE))
    (tmp_path / "after.json").write_text(json.dumps(AFTER))
    assert main([str(tmp_path / "before"), str(tmp_path / "after.json")]) == 0
    assert "4 common sequences" in capsys.readouterr().out
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "norows.json").write_text(json.dumps({"summary": {}}))
    (tmp_path / "broken.json").write_text(json.dumps({"rows": [{"sequence": "a"}]}))
    (tmp_path / "other.json").write_text(json.dumps(_results([_row("z", "room", 1.0, 1.0)], 1.0)))
    (tmp_path / "text.json").write_text(json.dumps({"rows": [_row("a", "room", 1.0, 1.0) | {"fused_over_best": "x"}]}))
    (tmp_path / "deep.json").write_text('{"rows": [' + "[" * 5000 + "]" * 5000 + "]}")
    for before, after in [("missing", "after.json"), ("bad.json", "after.json"), ("norows.json", "after.json"),
                          ("broken.json", "broken.json"), ("other.json", "after.json"), ("text.json", "text.json"),
                          ("deep.json", "deep.json"), ("x" * 300, "after.json")]:
        assert main([str(tmp_path / before), str(tmp_path / after)]) == 2, before
        err = capsys.readouterr().err
        assert err.startswith("python -m windowvo.scale_compare: error: ") and err.count("\n") == 1, err
