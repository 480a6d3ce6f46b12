"""Run a configured job end to end: load, process, write, evaluate, summarise.

The command line (``windowvo.cli.run``) calls :func:`run_and_report`; the benchmark and the tests call
:func:`run_job` to get the numbers (a :class:`JobReport`) without printing. A run whose wheel clock offset was
estimated and applied part way is made again from its first frame with that offset (:func:`second_pass_config`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config import Config, RerunMode, RunMode, WheelClockMode
from ..errors import WindowVOError
from ..io.sequence import Sequence
from ..io.trajectory import Trajectory
from . import stop
from .outfolder import FIRST_PASS_DIR, OutputLock, check_writable_names, keep_first_pass, restore_first_pass
from .outputs import summary_dict, summary_lines, write_outputs, write_summary
from .parallel import BackendWorker
from .pipeline import Pipeline, RunResult
from .progress import Progress

if TYPE_CHECKING:  # evo (and scipy under it) is loaded only to evaluate, after the run: a run without ground truth
    from ..eval.metrics import AccuracyReport  # never pays its import (about 0.4 s)

log = logging.getLogger("windowvo")


@dataclass
class JobReport:
    result: RunResult
    sequence: Sequence
    accuracy: AccuracyReport | None = None  # the smoothed trajectory
    wheel_accuracy: AccuracyReport | None = None
    online_accuracy: AccuracyReport | None = None  # the causal trajectory


def load_sequence(cfg: Config) -> Sequence:
    from .. import io

    return io.load(cfg)


def wheel_only_trajectory(seq: Sequence, timestamps: np.ndarray) -> Trajectory | None:
    """Wheel odometry alone at the given times, anchored at the first one (world = first base)."""
    odo = seq.odometry
    if odo is None or len(timestamps) == 0:
        return None
    poses = np.stack([odo.delta(float(timestamps[0]), float(t)) for t in timestamps])
    return Trajectory(np.asarray(timestamps, float), poses)


def make_viewer(cfg: Config, seq: Sequence):
    if cfg.viz.rerun is RerunMode.OFF:
        return None
    from ..viz.rerun_logger import RerunLogger

    return RerunLogger(cfg, seq)


def run_job(cfg: Config, progress=None) -> JobReport:
    """Run a job into ``cfg.output`` (holding its lock, :class:`~windowvo.runtime.outfolder.OutputLock`). A stop
    signal while loading raises :class:`~windowvo.runtime.stop.Interrupted`; from the first frame on, it ends the
    run early and every output is still written (``result.interrupted``)."""
    with stop.guarded(stop.Phase.RAISE), OutputLock.of(cfg.output):
        check_writable_names(cfg.output)
        # A summary.json that is not this run's must never sit beside this run's files (a failed run included).
        (cfg.output / "summary.json").unlink(missing_ok=True)
        report = _run_once(cfg, progress)
        second = second_pass_config(cfg, report.result)
        if second is not None and stop.requested() is None:
            report = _second_pass(cfg, second, report, progress)
        if stop.requested() is not None:  # a signal after the last frame: the run is still marked interrupted
            report.result.interrupted = True
        return report


def _run_once(cfg: Config, progress) -> JobReport:
    # Pipelined: spawn the back-end process first, so its start overlaps with loading the sequence.
    worker = BackendWorker() if cfg.run_mode is RunMode.PIPELINED else None
    try:
        return _run_job(cfg, progress, worker)
    finally:
        if worker is not None:
            worker.close()


# The first pass's summary.json records the offset its second pass reads the wheels at (ms) under this key.
SECOND_PASS_KEY = "second_pass_time_offset_ms"


def second_pass_config(cfg: Config, result: RunResult) -> Config | None:
    """The config of a second pass, or None when the run needs none: with ``backend.odometry.time_offset: estimate``
    and ``time_offset_second_pass``, a finished run whose wheel clock offset was applied part way (its keyframes
    before then hold wheel steps read at the camera's times) is made again with the wheels read at its final
    estimate from the first frame on (``time_offset: fixed``)."""
    o = cfg.backend.odometry
    c = result.wheel_time_offset
    if (o.time_offset is not WheelClockMode.ESTIMATE or not o.time_offset_second_pass or result.interrupted
            or c is None or c.applied_s is None or not (c.observable and math.isfinite(c.offset_s))):
        return None
    return _with_fixed_offset(cfg, 1000.0 * c.offset_s)


def _with_fixed_offset(cfg: Config, offset_ms: float) -> Config:
    odometry = cfg.backend.odometry.model_copy(update={"time_offset": WheelClockMode.FIXED, "time_offset_ms": offset_ms})
    return cfg.model_copy(update={"backend": cfg.backend.model_copy(update={"odometry": odometry})})


def resume_config(cfg: Config) -> Config:
    """The config a killed run in ``cfg.output`` is resumed with: a second pass's (its first pass finished, its
    files and summary in ``OUT/first_pass/``) when the run took one, else ``cfg``."""
    o = cfg.backend.odometry
    if o.time_offset is not WheelClockMode.ESTIMATE or not o.time_offset_second_pass:
        return cfg
    try:
        offset_ms = json.loads((cfg.output / FIRST_PASS_DIR / "summary.json").read_text()).get(SECOND_PASS_KEY)
    except (OSError, ValueError):
        return cfg
    if not isinstance(offset_ms, (int, float)) or not math.isfinite(offset_ms):
        return cfg
    log.info("resuming the second pass (the wheels read at %+.1f ms; the first pass's files in %s/)", offset_ms,
             FIRST_PASS_DIR)
    return _with_fixed_offset(cfg, float(offset_ms))


def _second_pass(cfg: Config, second: Config, first: JobReport, progress) -> JobReport:
    """Keep the first pass's files (with its summary) in ``OUT/first_pass/`` and make the run again with
    ``second``; the second pass's report, with the first pass's clock estimate. A second pass that fails or is
    stopped (Ctrl-C, SIGTERM) gives the first pass back: its files return to ``OUT`` and its report is returned."""
    c = first.result.wheel_time_offset
    assert c is not None and c.applied_s is not None
    try:
        kept = keep_first_pass(cfg.output)
        summary = summary_dict(first, cfg)
        summary[SECOND_PASS_KEY] = 1000.0 * c.offset_s  # exact: a killed second pass is resumed with it
        write_summary(summary, kept)
    except (OSError, WindowVOError) as err:  # e.g. a full disk: no second pass, the first pass stays the run
        restore_first_pass(cfg.output, drop_others=False)
        log.error("no second pass: the first pass's files could not be kept aside (%s); they are in %s", err,
                  cfg.output)
        return first
    log.info("wheel clock: %+.1f ms against the camera's, applied from t=%.2f s; the run again from its first frame "
             "with the wheels read at that offset (a second pass; the first pass's files are in %s)",
             1000.0 * c.offset_s, c.applied_since_t if c.applied_since_t is not None else float("nan"), kept)
    try:
        report = _run_once(second, progress)
    except (Exception, stop.Interrupted) as err:
        restore_first_pass(cfg.output)
        log.error("the second pass failed (%s); the first pass's results are in %s", err, cfg.output)
        return first
    if report.result.interrupted or stop.requested() is not None:
        restore_first_pass(cfg.output)
        log.warning("the second pass was stopped; the first pass's results are in %s", cfg.output)
        return first
    report.result.first_pass_clock = c
    return report


def _log_plan(pipe: Pipeline, seq: Sequence) -> None:
    plan = pipe.vo.plan
    ground = (f"the floor at the camera height ({plan.camera_height_m:.3f} m above it)" if plan.use_ground
              else "no ground cue")
    if pipe.use_odometry:
        label = " (synthetic)" if seq.odometry is not None and seq.odometry.synthetic else ""
        calib = ", calibrated online once the floor is in view" if plan.calibration_wanted else ""
        log.info("scale sources: wheel odometry%s%s; %s", label, calib, ground)
    elif plan.use_ground:
        log.info("no wheel odometry: monocular run, metric scale from %s once the floor is in view (up to scale before)", ground)
    else:
        log.warning("no wheel odometry and no ground cue: monocular run, the trajectory is up to scale")


def _run_job(cfg: Config, progress, worker: BackendWorker | None) -> JobReport:
    seq = load_sequence(cfg)
    for w in seq.warnings:
        log.warning("%s", w)
    viewer = make_viewer(cfg, seq)
    pipe = Pipeline(cfg, seq, viewer=viewer, progress=progress, worker=worker)
    _log_plan(pipe, seq)
    result = None
    try:
        result = pipe.run()
    finally:
        if result is None:  # an unexpected error: still write what we have
            try:
                write_outputs(cfg, pipe.result(interrupted=True), cfg.output)
                log.error("run failed after frame %d; partial results written to %s",
                          pipe.frames[-1][0] if pipe.frames else -1, cfg.output)
            except Exception:  # pragma: no cover - best effort only
                pass
            pipe.end_journal(None)
    write_outputs(cfg, result, cfg.output)
    pipe.end_journal("interrupted" if result.interrupted else "complete")
    if result.n_keyframes == 0 and not result.interrupted:
        if viewer is not None:
            viewer.finish(result, None)
        raise WindowVOError(
            f"no keyframe in {result.n_frames} frames: no trackable features (images black, uniform or fully "
            f"masked?); stats.csv in {cfg.output} says what each frame had")
    report = evaluate_report(JobReport(result, seq))
    if viewer is not None:
        viewer.finish(result, report)
    return report


def evaluate_report(report: JobReport) -> JobReport:
    """The accuracies of the report's trajectories against the sequence's ground truth (when it has one)."""
    seq, result = report.sequence, report.result
    if seq.groundtruth is None or len(result.trajectory) < 3:
        return report
    from ..eval.metrics import evaluate

    try:
        report.accuracy = evaluate(seq.groundtruth, result.trajectory, monocular=not result.metric)
        if result.trajectory_online is not None and len(result.trajectory_online) >= 3:
            report.online_accuracy = evaluate(seq.groundtruth, result.trajectory_online, monocular=not result.metric)
        wheel = wheel_only_trajectory(seq, result.trajectory.timestamps)
        if wheel is not None:
            report.wheel_accuracy = evaluate(seq.groundtruth, wheel)
    except WindowVOError as err:
        log.warning("evaluation skipped: %s", err)
    return report


def _progress_bar(cfg: Config, total: int):
    """The run's progress (a bar on a terminal, a line every 10% elsewhere) and its per-frame callback."""
    if not cfg.progress:
        return None, None
    bar = Progress(total or None, "frames")

    def update(n_frames: int, n_kf: int) -> None:
        bar.update(n_frames, keyframes=n_kf)

    return bar, update


def run_and_report(cfg: Config) -> RunResult:
    """Run a job with a progress bar, write ``summary.json`` and print the console summary."""
    seq_len_hint = None
    with contextlib.suppress(OSError):
        seq_len_hint = len(list((cfg.sequence / "images").iterdir())) if (cfg.sequence / "images").is_dir() else None
    total = min(seq_len_hint or 0, cfg.max_frames or 10**9) or None
    bar, update = _progress_bar(cfg, total or 0)
    with stop.guarded(stop.Phase.RAISE):
        try:
            report = run_job(cfg, progress=update)
        finally:
            if bar is not None:
                bar.close()
        stop.set_phase(stop.Phase.DEFER)  # from here on a signal only marks the run interrupted
        if stop.requested() is not None:
            report.result.interrupted = True
        summary = summary_dict(report, cfg)
        write_summary(summary, cfg.output)
        print("\n".join(summary_lines(report, summary, cfg.output)))
        return report.result
