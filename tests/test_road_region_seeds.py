"""``scripts/road_region_seeds.py``: two settings compared on held-out rendered sequences (a study tool); its bad
input and how its ``--seeds`` runs are chosen and summed up."""

from __future__ import annotations

import math

from conftest import load_script


def _script():
    return load_script("road_region_seeds")


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    mod = _script()
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert mod.main(["--work", str(tmp_path / "w"), "--seeds", "0"]) == 2
    assert mod.main(["--work", str(tmp_path / "w"), "--set", "backend.no_such_key=1"]) == 2
    assert mod.main(["--work", str(tmp_path / "w"), "--renders", str(blocker / "renders")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("road_region_seeds.py: error:") for line in err), err
    assert not (tmp_path / "w" / "out").exists()  # refused before any render or run


def test_the_ways_that_use_the_floor_run_once_per_seed():
    mod = _script()
    floor_ways = ("fused", "floor")
    assert mod.run_seeds("fused", 3, floor_ways) == [0, 1, 2]
    assert mod.run_seeds("floor", 2, floor_ways) == [0, 1]
    assert mod.run_seeds("wheels", 3, floor_ways) == [None]  # no floor: the seed changes nothing
    assert mod.run_seeds("fused", 1, floor_ways) == [None]  # one run at the config's own seed


def test_a_ways_ate_is_the_median_of_its_runs_with_an_ate():
    mod = _script()
    assert mod.median([0.3, 0.1, 0.2]) == 0.2
    assert mod.median([0.4, 0.1, 0.2, 0.3]) == 0.25
    assert math.isclose(mod.median([0.2, float("nan"), 0.4]), 0.3)  # a run without an ATE does not count
    assert math.isnan(mod.median([float("nan")]))
