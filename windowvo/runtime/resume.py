"""``python -m windowvo.run CONFIG --resume``: a killed run's folder continued to the end of the sequence.

What it does: it reads the run's journal (``journal.jsonl``, see ``runtime/journal.py``) and keeps every frame up
to the last keyframe that had left the fixed-lag window (its last *final* keyframe, frame ``k``): those frames
have exactly the poses the uninterrupted run ends with (the frames between two final keyframes placed as the
finished run places them), and their ``stats.csv`` rows. It then runs the sequence again from the killed run's
first frame (:func:`windowvo.io.sequence.subsequence`, the same config and run mode) and keeps its frames after
``k``. Runs are deterministic (the pipelined mode bit for bit the sequential one), so the frames up to ``k`` come
out as the killed run had them and the result is the uninterrupted run's, bit for bit: resuming costs the time of
the frames already done, and gives the run that was not killed. The replay is checked against the journal (the
final keyframes' poses): a difference (the code, the config or the machine changed since the kill) is a warning
and ``replay_max_difference_m`` in ``summary.json``; the continuation is then placed in the killed run's world at
``k``: ``T_world_base(j) = T_world_base_journal(k) @ T_start_base(j)`` with ``T_start_base(j)`` its pose of frame
``j`` relative to its own pose of frame ``k`` (:class:`~windowvo.runtime.journal.Seam`). A continuation from a
later frame (a shorter replay) was measured: a fresh back end lands within +-10-20% of the uninterrupted run's
ATE, not within 5% (docs/robustness.md). With wheels or the floor the continuation is metric by itself; a
monocular run with neither has an arbitrary scale per run, so the continuation's translations are scaled by the
least-squares fit of its keyframe positions to the killed run's causal keyframe positions over the frames both
ran (the killed run's journaled frames after ``k``; :func:`~windowvo.runtime.journal.overlap_scale`).

The outputs then cover the whole sequence: ``trajectory.txt`` and ``trajectory_online.txt`` (the killed run's
poses up to frame ``k``, the continuation's after it), ``stats.csv`` (the killed run's rows up to frame ``k``, the
continuation's after it, frame indices of the whole sequence), ``config_resolved.yaml`` and ``summary.json``
(``"resumed": true``, ``"resumed_from_frame": k``, ``"interrupted": false`` when the continuation reached the end,
the accuracy of the whole trajectory when the sequence has ground truth; the timings, the wheel calibration and
the other back-end statistics are the continuation's). No recording is made during the continuation.

The continuation journals into the same ``journal.jsonl`` as a new segment, so a kill during ``--resume`` is
resumed again the same way (from the last final keyframe of the journal as a whole). Ctrl-C or SIGTERM during the
continuation behave as in a run (the outputs of every finished frame are written, exit 130/143); such a folder
can be resumed again too. The folder's lock is held throughout. A folder whose run (or resume) finished
(``summary.json`` with ``"interrupted": false``) has nothing to resume.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..backend.report import ScaleReport
from ..config import Config, RunMode
from ..errors import WindowVOError
from ..io.sequence import Sequence, subsequence
from ..io.trajectory import Trajectory
from ..types import FrameRecord, ScaleSource
from . import stop
from .job import JobReport, evaluate_report, load_sequence, resume_config
from .journal import (
    JOURNAL_NAME,
    JournalContents,
    Seam,
    last_final_frame,
    mark_end,
    read_journal,
    resumed_trajectory,
    seam,
)
from .outfolder import OutputLock
from .outputs import summary_dict, summary_lines, write_outputs, write_summary
from .parallel import BackendWorker
from .pipeline import Pipeline, RunResult

log = logging.getLogger("windowvo")

# A replayed final keyframe further than this from the journal's pose means the replay is not the killed run's.
REPLAY_TOLERANCE_M = 1e-6


def resumed_result(j: JournalContents, interrupted: bool = True) -> RunResult:
    """A :class:`RunResult` of the journaled frames. What the back end knew about the scale (the wheel calibration,
    when the floor fixed it) died with the process: the scale sources are the cues the run was set up to use."""
    recs = j.records
    sources = [s.value for s, used in ((ScaleSource.WHEELS, j.header.get("use_odometry")),
                                       (ScaleSource.GROUND_PLANE, j.header.get("use_ground"))) if used]
    return RunResult(
        n_frames=len(recs),
        n_keyframes=sum(1 for r in recs if r.is_keyframe and r.backend_status),
        n_skipped=sum(1 for r in recs if r.note.startswith("skipped")),
        wall_s=0.0,
        trajectory=resumed_trajectory(j),
        records=recs,
        monocular=not j.header.get("use_odometry", False),
        scale=ScaleReport(metric=bool(sources), scale_sources=sources),
        interrupted=interrupted,
        frontend_ms=[r.frontend_ms for r in recs if r.frontend_ms > 0],
        backend_ms=[r.backend_ms for r in recs if r.is_keyframe],
        last_frame_index=recs[-1].frame_index,
        trajectory_online=Trajectory(j.timestamps, np.stack(j.online)),
    )


def check_resumable(j: JournalContents, out: Path) -> None:
    """Refuse (one line) a folder whose run finished, or whose journal holds no frame."""
    summary = out / "summary.json"
    finished = False
    if j.end is not None and summary.is_file():
        try:
            finished = json.loads(summary.read_text()).get("interrupted") is False
        except (OSError, ValueError, AttributeError):
            finished = False
    if finished:
        raise WindowVOError(f"nothing to resume in '{out}': that run ended and wrote its outputs (summary.json); "
                            "use --force to run again")
    if not j.records:
        raise WindowVOError(f"nothing to resume in '{out}': the run was stopped before its first keyframe "
                            "was finished; use --force to run again")


def start_frame(j: JournalContents) -> int:
    """The frame the continuation starts from: the journal's last final keyframe (the first frame without one)."""
    last = last_final_frame(j)
    return j.records[last].frame_index if last is not None else j.records[0].frame_index


def merged_result(j: JournalContents, sm: Seam, cont: RunResult) -> RunResult:
    """The killed run's frames up to the seam, the continuation's after it, in the killed run's world."""
    n = sm.n_prefix
    keep = [i for i, r in enumerate(cont.records) if r.frame_index > sm.first_frame]
    prefix = resumed_trajectory(j)
    traj, online = cont.trajectory, cont.trajectory_online
    records = j.records[:n] + [cont.records[i] for i in keep]
    kept = [i for i in keep if i < len(traj)]  # frames whose keyframe never came back from the back end: none
    poses = [*prefix.T_world_base[:n], *(sm.place(traj.T_world_base[i]) for i in kept)]
    times = [*prefix.timestamps[:n], *(traj.timestamps[i] for i in kept)]
    on = [*j.online[:n], *(sm.place(online.T_world_base[i]) for i in keep)] if online is not None else list(j.online)
    prev = j.records[:n]
    return RunResult(
        n_frames=len(records),
        n_keyframes=sum(1 for r in prev if r.is_keyframe and r.backend_status) + sum(
            1 for i in keep if cont.records[i].is_keyframe and cont.records[i].backend_status),
        n_skipped=sum(1 for r in records if r.note.startswith("skipped")),
        wall_s=cont.wall_s, trajectory=Trajectory(np.asarray(times, float), np.stack(poses)), records=records,
        monocular=cont.monocular, scale=cont.scale, interrupted=cont.interrupted,
        frontend_ms=cont.frontend_ms, backend_ms=cont.backend_ms, notes=cont.notes,
        last_frame_index=records[-1].frame_index,
        trajectory_online=Trajectory(np.asarray([r.timestamp for r in records[:len(on)]], float), np.stack(on)),
        wheel_time_offset=cont.wheel_time_offset)


def replay_difference_m(j: JournalContents, records: list[FrameRecord], traj: Trajectory, seam_frame: int) -> float:
    """Largest distance between the journal's final keyframe poses up to ``seam_frame`` and the replay's poses of
    the same frames (0 when the replay is the killed run, as it is with the same code, config and machine)."""
    row = {r.frame_index: i for i, r in enumerate(records)}
    diffs = [float(np.linalg.norm(T[:3, 3] - traj.T_world_base[row[f]][:3, 3]))
             for f, (_, T) in j.final_keyframes.items() if f <= seam_frame and f in row and row[f] < len(traj)]
    return max(diffs, default=0.0)


def run_continuation(cfg: Config, sub: Sequence, seam_frame: int) -> tuple[Pipeline, RunResult]:
    """A fresh pipeline on the sub-sequence, journaling into the folder's journal as a new segment."""
    worker = BackendWorker() if cfg.run_mode is RunMode.PIPELINED else None
    # The sub-sequence is already cut to the frames to run: the frame limit is applied.
    pipe = Pipeline(cfg.model_copy(update={"max_frames": None}), sub, worker=worker, continuation=seam_frame)
    result = None
    try:
        result = pipe.run()
    finally:
        if worker is not None:
            worker.close()
        if result is None:  # an unexpected error: the journal (and its new segment) stays for --resume
            pipe.end_journal(None)
    return pipe, result


def resume(cfg: Config) -> RunResult:
    """Continue the killed run in ``cfg.output`` to the end of its sequence; write the outputs, print the summary.
    A run killed in its second pass (``backend.odometry.time_offset_second_pass``) continues that pass; one killed
    in its first pass continues the first and takes no second."""
    cfg = resume_config(cfg)
    out = cfg.output
    with stop.guarded(stop.Phase.RAISE), OutputLock.of(out):
        j = read_journal(out / JOURNAL_NAME)
        check_resumable(j, out)
        k = start_frame(j)
        seq = load_sequence(cfg)
        n_total = min(len(seq), cfg.max_frames or len(seq))
        if n_total - k < 2:  # nothing after the last final keyframe to run: the journal is the whole run
            return _write(cfg, JobReport(resumed_result(j, j.records[-1].frame_index < n_total - 1), seq), k, None)
        k0 = j.records[0].frame_index
        log.info("resuming: the run again from frame %d (deterministic: the frames up to %d, the journal's last final "
                 "keyframe, as the killed run had them) to frame %d", k0, k, n_total - 1)
        pipe, cont = run_continuation(cfg, subsequence(seq, k0, n_total), k)
        at_k = [i for i, r in enumerate(cont.records) if r.frame_index == k]
        if not at_k or len(cont.trajectory) <= at_k[0]:  # stopped in its warm-up: the journal's frames only
            return _write(cfg, JobReport(resumed_result(j), seq), k, pipe)
        assert cont.trajectory_online is not None
        sm = seam(j, k, cont.records, list(cont.trajectory_online.T_world_base), cont.trajectory.T_world_base[at_k[0]])
        if not j.metric_cue:
            log.info("monocular run without a metric cue: the continuation scaled by %.4f (fit on the overlap)",
                     sm.scale)
        diff = replay_difference_m(j, cont.records, cont.trajectory, k)
        if diff > REPLAY_TOLERANCE_M:
            log.warning("the replay is not the killed run: its keyframes up to frame %d differ by up to %.4f m (the "
                        "code, the config or the machine changed since the kill); its frames after %d are placed "
                        "at the killed run's pose of frame %d", k, diff, k, k)
        merged = merged_result(j, sm, cont)
        if len(merged.records) < len(j.records):  # stopped before the killed run's last frame: keep that one's
            merged = resumed_result(j)
        return _write(cfg, JobReport(merged, seq), k, pipe, diff)


def _write(cfg: Config, report: JobReport, k: int, pipe: Pipeline | None, replay_diff_m: float | None = None
           ) -> RunResult:
    """Write the outputs (then close the journal's segment), ``summary.json`` and the console summary."""
    stop.set_phase(stop.Phase.DEFER)  # frames are computed: from here on a signal only marks the run interrupted
    result = report.result
    write_outputs(cfg, result, cfg.output)
    if stop.requested() is not None:
        result.interrupted = True
    if pipe is not None:
        pipe.end_journal("interrupted" if result.interrupted else "complete")
    else:
        mark_end(cfg.output / JOURNAL_NAME, "resumed")
    report = evaluate_report(report)
    summary = summary_dict(report, cfg)
    summary.update(resumed=True, resumed_from_frame=k,
                   replay_max_difference_m=None if replay_diff_m is None else round(replay_diff_m, 9))
    write_summary(summary, cfg.output)
    log.info("resumed from frame %d: %d frames in the outputs", k, result.n_frames)
    print("\n".join(summary_lines(report, summary, cfg.output)))
    return result
