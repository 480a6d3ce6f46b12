"""The per-stage CPU budget (runtime/stage_timer.py, tools/stage_budget.py): it covers every stage, a frame's
stages fit in the frame, and timing leaves the results unchanged. No assertion on any duration."""

from __future__ import annotations

import threading
import time

import pytest
from conftest import make_config

from windowvo.runtime import stage_timer
from windowvo.runtime.stage_timer import BACKEND_STAGES, STAGE_SCOPE, Scope, Stage
from windowvo.synth.paths import PathKind
from windowvo.tools.stage_budget import UNTIMED, budget, case_table

# Slack for float sums of the same clock's differences (ms).
EPS_MS = 1e-6
FRONT_STAGES = (Stage.DECODE, Stage.INPUT_CHECKS, Stage.GAIN, Stage.TRACKING, Stage.DETECTION, Stage.UNDISTORTION,
                Stage.RANSAC, Stage.KEYFRAME, Stage.RECORDING)


@pytest.fixture(scope="module")
def tiny_seq(seq_factory):
    return seq_factory("stage_budget", path=PathKind.LOOP, duration_s=2.0, seed=7)


@pytest.fixture(scope="module")
def timed_run(tiny_seq, tmp_path_factory):
    """A sequential run with the recording on, with the stage recorder running: its StageTimes and records."""
    from windowvo.runtime.job import run_job

    out = tmp_path_factory.mktemp("timed")
    with stage_timer.recording() as rec:
        rep = run_job(make_config(tiny_seq, out, viz={"rerun": "save"}))
        times = rec.times()
    return times, rep, out


def test_every_stage_is_timed_where_it_runs(timed_run):
    times, rep, _ = timed_run
    assert len(times.frames) == rep.result.n_frames
    assert [f.index for f in times.frames] == [r.frame_index for r in rep.result.records]
    assert [f.keyframe for f in times.frames] == [r.is_keyframe for r in rep.result.records]
    seen = set().union(*(f.ms for f in times.frames))
    assert set(FRONT_STAGES) <= seen
    assert set(BACKEND_STAGES) - {Stage.BACKEND_GUESS} <= seen  # the first keyframe needs no guess
    for f in times.frames:
        backend = {s for s in f.ms if STAGE_SCOPE[s] is Scope.KEYFRAME}
        if f.keyframe:
            assert {Stage.BACKEND_FACTORS, Stage.BACKEND_ISAM2, Stage.BACKEND_ESTIMATE} <= backend
        else:
            assert not backend
    assert Stage.OUTPUTS in times.after_stages_ms
    assert Stage.RECORDING in times.before_stages_ms  # the recording's set-up
    assert times.other_threads_ms.get(Stage.RECORDING_THREAD)  # its logging thread, kept apart
    assert Stage.RECORDING_THREAD not in seen


def test_stage_times_are_non_negative_and_fit_in_their_frame(timed_run):
    times, _, _ = timed_run
    for f in times.frames:
        assert all(v >= 0.0 for v in f.ms.values()), f
        assert f.stages_ms <= f.total_ms + EPS_MS, f
    assert times.before_frames_ms >= sum(times.before_stages_ms.values()) - EPS_MS
    assert times.after_frames_ms >= sum(times.after_stages_ms.values()) - EPS_MS
    assert all(v >= 0.0 for v in times.other_threads_ms[Stage.RECORDING_THREAD])


def test_timing_leaves_the_results_bit_for_bit(timed_run, tiny_seq, tmp_path):
    from windowvo.runtime.job import run_job

    _, _, out_on = timed_run
    run_job(make_config(tiny_seq, tmp_path, viz={"rerun": "save"}))
    for name in ("trajectory.txt", "trajectory_online.txt"):
        assert (out_on / name).read_bytes() == (tmp_path / name).read_bytes(), name


def test_the_budget_table_has_every_stage_and_shares_that_add_up(timed_run):
    res = budget(timed_run[0], "tiny", "640x480")
    stages = [r["stage"] for r in res["frame_rows"]]
    for s in Stage:
        if s is not Stage.OUTPUTS:
            assert any(label.startswith(s.value) for label in stages), s
    assert any(r["stage"].endswith(Stage.OUTPUTS.value) for r in res["run_rows"])
    assert UNTIMED in stages
    parts = sum(r["total_ms"] for r in res["frame_rows"]) + sum(r["total_ms"] for r in res["run_rows"])
    assert parts == pytest.approx(res["run_thread_ms"] + res["other_threads_timed_ms"], rel=1e-9)
    assert all(r["total_ms"] >= -EPS_MS for r in res["frame_rows"] + res["run_rows"])
    table = case_table(res)
    assert table.count("\n") == len(res["frame_rows"]) + len(res["run_rows"]) + 2
    assert res["keyframes"] >= 2 and res["frames"] > res["keyframes"]


def test_off_the_timers_are_a_shared_no_op():
    assert stage_timer.section(Stage.DECODE) is stage_timer.section(Stage.RANSAC)
    lap = stage_timer.Laps()
    assert lap.rec is None
    lap(Stage.DECODE)  # nothing to add to: must not fail
    stage_timer.begin_frame(0)
    stage_timer.mark_keyframe()
    stage_timer.end_frames()


def test_other_threads_go_to_their_own_lists_and_one_recorder_at_a_time():
    with stage_timer.recording() as rec:
        with pytest.raises(RuntimeError), stage_timer.recording():
            pass
        stage_timer.begin_frame(3)

        def other() -> None:
            with stage_timer.section(Stage.RECORDING_THREAD):
                time.sleep(0)
            stage_timer.begin_frame(99)  # not the run's thread: ignored

        t = threading.Thread(target=other)
        t.start()
        t.join()
        with stage_timer.section(Stage.DECODE):
            pass
        times = rec.times()
    assert [f.index for f in times.frames] == [3]
    assert set(times.frames[0].ms) == {Stage.DECODE}
    assert len(times.other_threads_ms[Stage.RECORDING_THREAD]) == 1
    assert stage_timer.section(Stage.DECODE) is stage_timer.section(Stage.GAIN)  # off again


def test_the_shares_are_of_every_thread_and_add_up_to_the_whole(timed_run):
    res = budget(timed_run[0], "tiny", "640x480")
    for untimed in (None, 0.25 * res["run_thread_ms"]):
        r = res if untimed is None else {**res, "untimed_threads_ms": untimed}
        rows = [line for line in case_table(r).splitlines()[2:] if line.rstrip(" |").endswith("%")]
        shares = [float(line.rstrip(" |").rsplit("|", 1)[1].strip().rstrip("%")) for line in rows]
        assert len(rows) == len(r["frame_rows"]) + len(r["run_rows"]) + (untimed is not None)
        assert sum(shares) == pytest.approx(100.0, abs=0.05 * len(shares) + 1e-9)


def test_the_stages_suite_takes_overrides(tmp_path, monkeypatch):
    """`bench --suite stages --set KEY=VALUE` reaches each case's job; the run mode stays sequential."""
    from windowvo.tools import stage_budget

    seen = {}
    monkeypatch.setattr(stage_budget, "measure_job", lambda cfg, name="": seen.setdefault("cfg", cfg))
    from windowvo.tools.bench import CaseKind, SeqCase

    tiny = SeqCase("tiny", CaseKind.SYNTH, spec=dict(duration_s=0.3, width=64, height=48, fx=40.0))
    stage_budget.budget_job(tiny, str(tmp_path), str(tmp_path / "out"), ("backend.max_landmarks=80", "run_mode=pipelined"))
    cfg = seen["cfg"]
    assert cfg.backend.max_landmarks == 80 and cfg.run_mode.value == "sequential"
