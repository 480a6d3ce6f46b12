"""The scale suite's comparison of two results (``python -m windowvo.scale_compare``): the distribution of the ratios
per way and scene, the seeds' spread, and clear errors for what is not a result."""

from __future__ import annotations

import json

import pytest

from windowvo.cli.scale_compare import main
from windowvo.tools.scale_compare import compare, comparison_text


def _row(name: str, scene: str, fused: float, floor: float, runs: list[float] | None = None) -> dict:
    fused_way = {"se3": fused, "sim3": fused}
    if runs is not None:
        fused_way["se3_runs"] = runs
    return {"sequence": name, "scene": scene, "fused": fused_way, "floor": {"se3": floor, "sim3": floor},
            "fused_over_best": fused / floor}


def _results(rows: list[dict], gmean: float) -> dict:
    return {"rows": rows, "summary": {"fused_over_best_gmean": gmean, "sequences": len(rows)}}


BEFORE = _results([_row("a", "room", 0.010, 0.020, [0.009, 0.010, 0.012]),
                   _row("b", "room", 0.040, 0.020, [0.030, 0.040, 0.050]),
                   _row("c", "street", 0.100, 0.200, [0.090, 0.100, 0.110]),
                   _row("gone", "street", 1.0, 1.0)], 0.8)
AFTER = _results([_row("a", "room", 0.020, 0.020),  # twice as bad, beyond the old seeds' runs
                  _row("b", "room", 0.045, 0.020),  # worse, but within the old seeds' spread: chance
                  _row("c", "street", 0.050, 0.100),  # half, beyond the old runs
                  _row("new", "street", 1.0, 1.0)], 0.7)


def test_the_ratios_are_judged_per_way_and_scene_against_the_old_seeds():
    c = compare(BEFORE, AFTER)
    assert [s.sequence for s in c.sequences] == ["a", "b", "c"]
    assert c.only_before == ["gone"] and c.only_after == ["new"]
    fused, floor = c.ways
    assert fused.way == "fused" and fused.gmean == pytest.approx((2.0 * 1.125 * 0.5) ** (1 / 3))
    assert (fused.worst, fused.worst_sequence) == (pytest.approx(2.0), "a")
    assert (fused.best, fused.best_sequence) == (pytest.approx(0.5), "c")
    assert fused.by_scene == {"room": pytest.approx((2.0 * 1.125) ** 0.5), "street": pytest.approx(0.5)}
    assert (fused.beyond_seeds_better, fused.beyond_seeds_worse) == (1, 1)
    assert (floor.beyond_seeds_better, floor.beyond_seeds_worse) == (0, 0)  # no seeded runs: never judged
    assert floor.gmean == pytest.approx(0.5 ** (1 / 3))
    assert c.summary == {"fused_over_best_gmean": (0.8, 0.7)}
    text = comparison_text(c)
    assert "| a | 0.010 | 0.020 | 2.00x (worse) |" in text and "| c | 0.100 | 0.050 | 0.50x (better) |" in text
    assert "only before: gone" in text and "fused_over_best_gmean: 0.800 -> 0.700" in text


def test_the_command_line_reads_a_benchmark_folder_and_refuses_what_is_not_a_result(tmp_path, capsys):
    (tmp_path / "before" / "scale").mkdir(parents=True)
    (tmp_path / "before" / "scale" / "scale_suite.json").write_text(json.dumps(BEFORE))
    (tmp_path / "after.json").write_text(json.dumps(AFTER))
    assert main([str(tmp_path / "before"), str(tmp_path / "after.json")]) == 0
    assert "3 common sequences" in capsys.readouterr().out
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "norows.json").write_text(json.dumps({"summary": {}}))
    (tmp_path / "broken.json").write_text(json.dumps({"rows": [{"sequence": "a"}]}))
    (tmp_path / "other.json").write_text(json.dumps(_results([_row("z", "room", 1.0, 1.0)], 1.0)))
    for before, after in [("missing", "after.json"), ("bad.json", "after.json"), ("norows.json", "after.json"),
                          ("broken.json", "broken.json"), ("other.json", "after.json")]:
        assert main([str(tmp_path / before), str(tmp_path / after)]) == 2, before
        err = capsys.readouterr().err
        assert err.startswith("python -m windowvo.scale_compare: error: ") and err.count("\n") == 1, err
