"""``python -m windowvo.run CONFIG --resume``: a killed run's folder turned into the full set of outputs.

What it does (and does not): it rebuilds the outputs from the run's journal (``journal.jsonl``, see
``runtime/journal.py``), it does not process frames again. ``trajectory.txt`` holds every frame the killed run
had finished: the keyframes that had left the fixed-lag window with their final smoothed poses (exactly the poses
the uninterrupted run ends with), the frames between them placed as the finished run places them, and the few
frames after the last final keyframe moved on from it by the causal estimate. ``stats.csv``,
``trajectory_online.txt``, ``config_resolved.yaml`` and ``summary.json`` (``"resumed": true``,
``"interrupted": true``, the accuracy when the sequence has ground truth) are written as a finished run writes
them. To process the rest of the sequence, run again with ``--force`` (the killed run's files are moved aside).
"""

from __future__ import annotations

import logging

import numpy as np

from ..backend.report import ScaleReport
from ..config import Config
from ..errors import WindowVOError
from ..io.trajectory import Trajectory
from ..types import ScaleSource
from .job import JobReport, evaluate_report, load_sequence
from .journal import JOURNAL_NAME, JournalContents, last_final_frame, mark_end, read_journal, resumed_trajectory
from .outfolder import OutputLock
from .outputs import summary_dict, summary_lines, write_outputs, write_summary
from .pipeline import RunResult

log = logging.getLogger("windowvo")


def resumed_result(j: JournalContents) -> RunResult:
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
        interrupted=True,
        frontend_ms=[r.frontend_ms for r in recs if r.frontend_ms > 0],
        backend_ms=[r.backend_ms for r in recs if r.is_keyframe],
        last_frame_index=recs[-1].frame_index,
        trajectory_online=Trajectory(j.timestamps, np.stack(j.online)),
    )


def resume(cfg: Config) -> RunResult:
    """Write the outputs of the killed run in ``cfg.output`` from its journal; print its summary."""
    out = cfg.output
    with OutputLock.of(out):
        j = read_journal(out / JOURNAL_NAME)
        if j.end is not None and (out / "summary.json").is_file():
            raise WindowVOError(f"nothing to resume in '{out}': that run ended and wrote its outputs (summary.json); "
                                "use --force to run again")
        if not j.records:
            raise WindowVOError(f"nothing to resume in '{out}': the run was stopped before its first keyframe "
                                "was finished; use --force to run again")
        result = resumed_result(j)
        report = evaluate_report(JobReport(result, load_sequence(cfg)))
        write_outputs(cfg, result, out)
        summary = summary_dict(report, cfg)
        last = last_final_frame(j)
        summary.update(resumed=True, final_keyframes=len(j.final_keyframes),
                       smoothed_through_frame=None if last is None else j.records[last].frame_index)
        write_summary(summary, out)
        mark_end(out / JOURNAL_NAME, "resumed")
        log.info("resumed from %s: %d frames finished, %d keyframes with final smoothed poses", JOURNAL_NAME,
                 result.n_frames, len(j.final_keyframes))
        print("\n".join(summary_lines(report, summary, out)))
        return result
