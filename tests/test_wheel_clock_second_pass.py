"""The wheel clock's second pass (``backend.odometry.time_offset_second_pass``): a recorded run whose offset was
estimated and applied part way is made again from its first frame with the wheels read at the final estimate.

Unit tests of when it is taken, of the first pass's files kept beside it, and of the config a killed second pass
is resumed with; the end-to-end case (the scale suite's stop-and-go room with its wheels 30 ms late) is in
``tests/test_wheel_clock_speed.py::test_a_late_clock_on_a_stop_and_go_drive`` (it shares that render).
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import pytest

from windowvo.backend.wheel_clock import ClockEstimate
from windowvo.config import WheelClockMode, config_from_dict
from windowvo.runtime.job import SECOND_PASS_KEY, resume_config, second_pass_config
from windowvo.runtime.outfolder import FIRST_PASS_DIR, keep_first_pass, move_aside, previous_run_files, remove_previous

APPLIED = ClockEstimate(0.0309, 0.0029, True, 26, True, applied_s=0.0316, applied_since_t=9.2, from_speed=True)


def _cfg(tmp_path, **odometry):
    return config_from_dict({"sequence": str(tmp_path / "seq"), "output": str(tmp_path / "out"),
                             "backend": {"odometry": odometry}})


def _result(clock=APPLIED, interrupted=False):
    return SimpleNamespace(wheel_time_offset=clock, interrupted=interrupted)


def test_a_run_whose_offset_was_applied_part_way_is_made_again_at_its_final_estimate(tmp_path):
    cfg = _cfg(tmp_path)
    second = second_pass_config(cfg, _result())
    assert second is not None
    o = second.backend.odometry
    assert o.time_offset is WheelClockMode.FIXED and o.time_offset_ms == pytest.approx(30.9)  # the estimate, not
    # the offset applied last (31.6 ms): the final estimate holds every interval of the run
    assert cfg.backend.odometry.time_offset is WheelClockMode.ESTIMATE  # the user's config is not changed
    assert second.output == cfg.output and second.sequence == cfg.sequence


@pytest.mark.parametrize("case", ["not applied", "not observable", "nan", "interrupted", "off", "fixed",
                                  "disabled", "no wheels"])
def test_no_second_pass(tmp_path, case):
    odometry: dict = {}
    clock: ClockEstimate | None = APPLIED
    interrupted = False
    if case == "not applied":
        clock = ClockEstimate(0.0309, 0.0029, True, 26, False)
    elif case == "not observable":
        clock = ClockEstimate(0.0, math.nan, False, 4, False, applied_s=0.01, applied_since_t=3.0)
    elif case == "nan":
        clock = ClockEstimate(math.nan, math.nan, True, 26, True, applied_s=0.01, applied_since_t=3.0)
    elif case == "interrupted":
        interrupted = True
    elif case == "off":
        odometry = {"time_offset": "off"}
    elif case == "fixed":
        odometry = {"time_offset": "fixed", "time_offset_ms": 30.0}
    elif case == "disabled":
        odometry = {"time_offset_second_pass": False}
    else:
        clock = None
    assert second_pass_config(_cfg(tmp_path, **odometry), _result(clock, interrupted)) is None


def test_the_first_pass_files_are_kept_and_count_as_an_earlier_run(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    for name in ("trajectory.txt", "stats.csv", "journal.jsonl"):
        (out / name).write_text(name)
    (out / ".windowvo.lock").write_text("1")
    (out / FIRST_PASS_DIR).mkdir()
    (out / FIRST_PASS_DIR / "stale.txt").write_text("an earlier first pass")
    kept = keep_first_pass(out)
    assert sorted(p.name for p in kept.iterdir()) == ["journal.jsonl", "stats.csv", "trajectory.txt"]
    assert (kept / "stats.csv").read_text() == "stats.csv"
    assert (out / ".windowvo.lock").exists() and not (out / "stats.csv").exists()  # the lock stays
    assert previous_run_files(out) == [out / FIRST_PASS_DIR]  # an earlier run: the command line asks for --force
    aside = move_aside(out)
    assert aside is not None and (aside / FIRST_PASS_DIR / "stats.csv").exists()
    keep_first_pass(out)
    assert remove_previous(out) == 1 and not (out / FIRST_PASS_DIR).exists()


def test_a_killed_second_pass_is_resumed_as_the_second_pass(tmp_path):
    cfg = _cfg(tmp_path)
    assert resume_config(cfg) is cfg  # no first pass: the run resumed as it was
    first = cfg.output / FIRST_PASS_DIR
    first.mkdir(parents=True)
    (first / "summary.json").write_text(json.dumps({"interrupted": False, SECOND_PASS_KEY: 30.922724063946394}))
    resumed = resume_config(cfg)
    assert resumed.backend.odometry.time_offset is WheelClockMode.FIXED
    assert resumed.backend.odometry.time_offset_ms == 30.922724063946394  # exactly: the replay is the killed run's
    off = _cfg(tmp_path, time_offset="off")
    assert resume_config(off) is off  # a run that never takes a second pass
    (first / "summary.json").write_text("{not json")
    assert resume_config(cfg) is cfg


@pytest.mark.parametrize("how", ["fails", "stopped"])
def test_a_second_pass_that_fails_or_is_stopped_gives_the_first_pass_back(tmp_path, monkeypatch, how):
    """The first pass is a finished run: a second pass that raises, or is stopped part way (its files partial),
    must not cost it. Its files come back to OUT and its report is the run's."""
    from windowvo.runtime import job

    cfg = _cfg(tmp_path)
    out = cfg.output
    out.mkdir(parents=True)
    for name in ("trajectory.txt", "stats.csv"):
        (out / name).write_text(f"first pass {name}")
    first = SimpleNamespace(result=SimpleNamespace(wheel_time_offset=APPLIED, interrupted=False))

    def second_pass(second_cfg, progress):
        assert second_cfg.backend.odometry.time_offset is WheelClockMode.FIXED
        assert (out / FIRST_PASS_DIR / "trajectory.txt").read_text() == "first pass trajectory.txt"
        (out / "trajectory.txt").write_text("a partial second pass")
        if how == "fails":
            raise RuntimeError("the back end failed")
        return SimpleNamespace(result=SimpleNamespace(interrupted=True))

    monkeypatch.setattr(job, "_run_once", second_pass)
    monkeypatch.setattr(job, "summary_dict", lambda report, c: {"interrupted": False})
    report = job._second_pass(cfg, second_pass_config(cfg, first.result), first, None)
    assert report is first
    assert (out / "trajectory.txt").read_text() == "first pass trajectory.txt"
    assert (out / "stats.csv").read_text() == "first pass stats.csv"
    assert not (out / FIRST_PASS_DIR).exists()


@pytest.mark.parametrize("where", ["moving", "summary"])
def test_a_first_pass_that_cannot_be_kept_aside_stays_the_run(tmp_path, monkeypatch, where):
    """A full disk while the first pass's files move to ``first_pass/`` (part way) or while its summary is written
    there: no second pass, every first-pass file back in OUT, the first pass's report returned, no traceback."""
    import os

    from windowvo.runtime import job, outfolder

    cfg = _cfg(tmp_path)
    out = cfg.output
    out.mkdir(parents=True)
    for name in ("trajectory.txt", "stats.csv", "journal.jsonl"):
        (out / name).write_text(f"first pass {name}")
    first = SimpleNamespace(result=SimpleNamespace(wheel_time_offset=APPLIED, interrupted=False))
    full = OSError(28, "No space left on device")
    if where == "moving":
        real = os.replace
        moved = []

        def replace_then_full(a, b):
            if len(moved) == 1:
                raise full
            moved.append(a)
            real(a, b)

        monkeypatch.setattr(outfolder.os, "replace", replace_then_full)
        monkeypatch.setattr(job, "restore_first_pass", lambda o, drop_others=True: (
            monkeypatch.setattr(outfolder.os, "replace", real), outfolder.restore_first_pass(o, drop_others)))
    else:
        def no_space(summary, folder):
            raise full

        monkeypatch.setattr(job, "write_summary", no_space)
    monkeypatch.setattr(job, "summary_dict", lambda report, c: {})
    monkeypatch.setattr(job, "_run_once", lambda *a: pytest.fail("no second pass may run"))
    assert job._second_pass(cfg, second_pass_config(cfg, first.result), first, None) is first
    for name in ("trajectory.txt", "stats.csv", "journal.jsonl"):
        assert (out / name).read_text() == f"first pass {name}"
    assert not (out / FIRST_PASS_DIR).exists()
