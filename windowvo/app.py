"""Run a configured job end to end: load, process, write, evaluate, summarise.

The command line (``run.py``) and the benchmark call :func:`run_and_report`; tests call
:func:`run_job` to get the numbers without printing.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
from dataclasses import dataclass

import numpy as np

from .backend.ground import levelled_mount, normal_from_tilt_deg, tilt_significant
from .config import Config, RerunMode, RunMode
from .errors import WindowVOError
from .eval.metrics import AccuracyReport
from .io.sequence import Sequence
from .io.trajectory import Trajectory
from .parallel import BackendWorker
from .pipeline import Pipeline, RunResult, write_outputs
from .types import FrameRecord

log = logging.getLogger("windowvo")


@dataclass
class JobReport:
    result: RunResult
    sequence: Sequence
    accuracy: AccuracyReport | None = None  # the smoothed trajectory
    wheel_accuracy: AccuracyReport | None = None
    online_accuracy: AccuracyReport | None = None  # the causal trajectory


def load_sequence(cfg: Config) -> Sequence:
    from . import io

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
    from .viz.rerun_logger import RerunLogger

    return RerunLogger(cfg, seq)


def run_job(cfg: Config, progress=None) -> JobReport:
    # Pipelined: spawn the back-end process first, so its start overlaps with loading the sequence.
    worker = BackendWorker() if cfg.run_mode is RunMode.PIPELINED else None
    try:
        return _run_job(cfg, progress, worker)
    finally:
        if worker is not None:
            worker.close()


def _run_job(cfg: Config, progress, worker: BackendWorker | None) -> JobReport:
    seq = load_sequence(cfg)
    for w in seq.warnings:
        log.warning("%s", w)
    viewer = make_viewer(cfg, seq)
    pipe = Pipeline(cfg, seq, viewer=viewer, progress=progress, worker=worker)
    be = pipe.backend
    ground = (f"the floor at the camera height ({be.camera_height_m:.3f} m above it)" if be.use_ground
              else "no ground cue")
    if pipe.use_odometry:
        label = " (synthetic)" if seq.odometry is not None and seq.odometry.synthetic else ""
        calib = ", calibrated online" if be.calibrate else ""
        log.info("scale sources: wheel odometry%s%s; %s", label, calib, ground)
    elif be.use_ground:
        log.info("no wheel odometry: monocular run made metric by %s", ground)
    else:
        log.warning("no wheel odometry and no ground cue: monocular run, the trajectory is up to scale")
    result = None
    try:
        result = pipe.run()
    finally:
        if result is None:  # an unexpected error: still write what we have
            try:
                pipe._close_journal()
                partial = RunResult(len(pipe.frames), len(pipe.kf_frames), 0, 0.0, pipe.assemble_trajectory(),
                                    pipe.records, not pipe.use_odometry, interrupted=True,
                                    trajectory_online=pipe.vo.online_trajectory(), **pipe.vo.scale_report())
                write_outputs(cfg, partial, cfg.output)
                log.error("run failed after frame %d; partial results written to %s",
                          pipe.frames[-1][0] if pipe.frames else -1, cfg.output)
            except Exception:  # pragma: no cover - best effort only
                pass
    write_outputs(cfg, result, cfg.output)
    if result.n_keyframes == 0 and not result.interrupted:
        if viewer is not None:
            viewer.finish(result, None)
        raise WindowVOError(
            f"no keyframe in {result.n_frames} frames: no trackable features (images black, uniform or fully "
            f"masked?); stats.csv in {cfg.output} says what each frame had")
    report = JobReport(result, seq)
    if seq.groundtruth is not None and len(result.trajectory) >= 3:
        from .eval.metrics import evaluate

        try:
            report.accuracy = evaluate(seq.groundtruth, result.trajectory, monocular=not result.metric)
            if result.trajectory_online is not None and len(result.trajectory_online) >= 3:
                report.online_accuracy = evaluate(seq.groundtruth, result.trajectory_online,
                                                  monocular=not result.metric)
            wheel = wheel_only_trajectory(seq, result.trajectory.timestamps)
            if wheel is not None:
                report.wheel_accuracy = evaluate(seq.groundtruth, wheel)
        except WindowVOError as err:
            log.warning("evaluation skipped: %s", err)
    if viewer is not None:
        viewer.finish(result, report)
    return report


def floor_summary(records: list[FrameRecord], T_base_cam: np.ndarray | None = None) -> dict:
    """What the run learnt about the floor: how much the base rocked (median over keyframes of
    ``base_rocking_deg``, None when never judged), at how many keyframes floor points were tied to the floor in
    a level frame because of it, the floor's tilt in the base frame at the end (None: too few floor fits), at how
    many keyframes the learnt normal was used, and ``T_base_cam`` corrected by that tilt (when given)."""
    rocking = [rec.base_rocking_deg for rec in records if rec.is_keyframe and np.isfinite(rec.base_rocking_deg)]
    tilts = [(rec.floor_tilt_x_deg, rec.floor_tilt_y_deg, rec.floor_tilt_se_deg) for rec in records
             if rec.is_keyframe and np.isfinite(rec.floor_tilt_x_deg)]
    return {"base_rocking_deg_median": round(float(np.median(rocking)), 4) if rocking else None,
            "level_frame_keyframes": sum(1 for rec in records if rec.level_frame),
            "floor_tilt_deg": None if not tilts else [round(float(v), 3) for v in tilts[-1][:2]],
            "floor_tilt_se_deg": None if not tilts else round(float(tilts[-1][2]), 3),
            "floor_normal_learnt_keyframes": sum(1 for rec in records if rec.floor_normal_learnt),
            "T_base_cam_levelled": None if not tilts or T_base_cam is None else [
                round(float(v), 6) for v in levelled_mount(T_base_cam, normal_from_tilt_deg(*tilts[-1][:2])).ravel()]}



def _progress_bar(cfg: Config, total: int):
    if not cfg.progress or not sys.stderr.isatty():
        return None, None
    from tqdm import tqdm

    bar = tqdm(total=total, unit="frame", dynamic_ncols=True, file=sys.stderr)

    def update(n_frames: int, n_kf: int) -> None:
        bar.n = n_frames
        bar.set_postfix(keyframes=n_kf, refresh=False)
        bar.refresh() if n_frames % 10 == 0 else None

    return bar, update


def run_and_report(cfg: Config) -> RunResult:
    seq_len_hint = None
    with contextlib.suppress(OSError):
        seq_len_hint = len(list((cfg.sequence / "images").iterdir())) if (cfg.sequence / "images").is_dir() else None
    total = min(seq_len_hint or 0, cfg.max_frames or 10**9) or None
    bar, update = _progress_bar(cfg, total or 0)
    try:
        report = run_job(cfg, progress=update)
    finally:
        if bar is not None:
            bar.close()
    r = report.result
    summary = {
        "frames": r.n_frames,
        "keyframes": r.n_keyframes,
        "skipped_frames": r.n_skipped,
        "wall_s": round(r.wall_s, 3),
        "fps": round(r.fps, 2),
        "frontend_ms_mean": round(float(np.mean(r.frontend_ms)), 3) if r.frontend_ms else None,
        "backend_ms_median": round(float(np.median(r.backend_ms)), 3) if r.backend_ms else None,
        "backend_resets": r.n_resets,
        "run_mode": cfg.run_mode.value,
        "monocular": r.monocular,
        "metric": r.metric,
        "scale_sources": r.scale_sources,
        "metric_from_frame": r.metric_from_frame,
        "floor_scale_reanchors": r.floor_scale_reanchors,
        "floor_untied": r.floor_untied,
        "wheel_calibration": None if r.wheel_calibration is None else {
            "scale": round(r.wheel_calibration.scale, 5), "scale_sigma": round(r.wheel_calibration.scale_sigma, 5),
            "yaw_bias_per_m": round(r.wheel_calibration.yaw_bias_per_m, 6),
            "yaw_bias_sigma": round(r.wheel_calibration.yaw_bias_sigma, 6)},
        "odometry_synthetic": bool(report.sequence.odometry is not None and report.sequence.odometry.synthetic),
        "interrupted": r.interrupted,
        **floor_summary(r.records, report.sequence.camera.T_base_cam),
        "accuracy": report.accuracy.as_dict() if report.accuracy is not None else None,
        "accuracy_online": report.online_accuracy.as_dict() if report.online_accuracy is not None else None,
        "wheel_only_accuracy": report.wheel_accuracy.as_dict() if report.wheel_accuracy is not None else None,
    }
    (cfg.output / "summary.json").write_text(json.dumps(summary, indent=2))
    lines = [
        f"windowvo: {r.n_frames} frames ({r.n_skipped} skipped), {r.n_keyframes} keyframes, "
        f"{r.wall_s:.1f} s, {r.fps:.1f} fps" + (" [interrupted]" if r.interrupted else ""),
    ]
    if not r.metric:
        lines.append("monocular run (no wheel odometry, no floor at the camera height): the trajectory is up to scale")
    else:
        synthetic = " (wheels synthetic, see odometry.csv header)" if summary["odometry_synthetic"] else ""
        late = (f", from frame {r.metric_from_frame} on (the floor came into view there; the trajectory before it "
                f"is rescaled)" if r.metric_from_frame is not None else "")
        n_re = r.floor_scale_reanchors
        drift = f"; the floor taken back after a scale drift at {n_re} keyframe{'s' * (n_re != 1)}" if n_re else ""
        lines.append("metric scale from: " + ", ".join(r.scale_sources) + synthetic + late + drift)
    if r.wheel_calibration is not None:
        c = r.wheel_calibration
        lines.append(f"wheel calibration: scale {c.scale:.4f} ± {c.scale_sigma:.4f}, "
                     f"yaw bias {c.yaw_bias_per_m * 1000:.2f} ± {c.yaw_bias_sigma * 1000:.2f} mrad/m")
    floor = []
    if summary["base_rocking_deg_median"] is not None:
        floor.append(f"base rocking {summary['base_rocking_deg_median']:.2f} deg between keyframes (level frame at "
                     f"{summary['level_frame_keyframes']} keyframes)")
    if summary["floor_tilt_deg"] is not None:
        tx, ty = summary["floor_tilt_deg"]
        n_used = summary["floor_normal_learnt_keyframes"]
        used = f"used at {n_used} keyframes" if n_used else "not used"
        se = summary["floor_tilt_se_deg"]
        floor.append(f"tilted {np.hypot(tx, ty):.2f} ± {se:.2f} deg in the base frame ({tx:+.2f} x, {ty:+.2f} y; "
                     f"{used})")
        significant = tilt_significant(float(np.hypot(tx, ty)), se)
        if significant and not n_used:
            log.warning("the floor is tilted %.2f deg in the base frame: T_base_cam's pitch or roll looks off by about "
                        "that, which biases the ground cue's scale (0.5 deg: about 3%%); correct T_base_cam (summary.json: "
                        "T_base_cam_levelled) or set backend.ground.mount_calibration: auto or on", np.hypot(tx, ty))
        elif significant:
            floor.append("T_base_cam levelled by it in summary.json (T_base_cam_levelled)")
    if r.floor_untied:
        floor.append(f"{r.floor_untied} floor landmarks found off it in later views and untied (a kerb or mat beside "
                     f"it; backend.ground.untie_sigmas)")
    if floor:
        lines.append("floor: " + "; ".join(floor))
    if report.accuracy is not None:
        lines.append("accuracy (smoothed): " + report.accuracy.summary(metric=r.metric))
    if report.online_accuracy is not None:
        lines.append("accuracy (causal, online): " + report.online_accuracy.summary(metric=r.metric))
    if report.wheel_accuracy is not None:
        lines.append(f"wheel odometry alone: ATE SE(3) {report.wheel_accuracy.ate_se3_rmse_m:.3f} m")
    lines.append(f"outputs: {cfg.output}")
    print("\n".join(lines))
    return r
