"""What a run leaves on disk and prints: trajectories, ``stats.csv``, the resolved config, ``summary.json``
and the console summary. Everything here is built from a :class:`~windowvo.runtime.job.JobReport`."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..backend.ground import levelled_mount, normal_from_tilt_deg, tilt_significant
from ..config import Config, save_config
from ..frontend.rocking import ROCKING_NOTE
from ..io.trajectory import write_tum
from ..types import FrameRecord
from .outfolder import FIRST_PASS_DIR
from .pipeline import ONLINE_HEADER, RunResult
from .stage_timer import Stage, section

if TYPE_CHECKING:  # pragma: no cover
    from .job import JobReport

log = logging.getLogger("windowvo")


def write_outputs(cfg: Config, result: RunResult, out: Path) -> None:
    """The trajectories, ``stats.csv`` and the resolved config."""
    with section(Stage.OUTPUTS):
        _write_outputs(cfg, result, out)


def _write_outputs(cfg: Config, result: RunResult, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    header = "T_world_base, world = base at the first frame (TUM: t tx ty tz qx qy qz qw)"
    if not result.metric:
        header += "\nmonocular run: translation is up to scale"
    elif result.scale_sources:
        header += "\nmetric scale from: " + ", ".join(result.scale_sources)
    write_tum(out / "trajectory.txt", result.trajectory.timestamps, result.trajectory.T_world_base,
              header="windowvo estimate (fixed-lag smoothed): " + header)
    if result.trajectory_online is not None and len(result.trajectory_online):
        write_tum(out / "trajectory_online.txt", result.trajectory_online.timestamps,
                  result.trajectory_online.T_world_base, header=ONLINE_HEADER + ": " + header)
    write_stats(out / "stats.csv", result.records)
    tmp = out / "config_resolved.yaml.tmp"
    save_config(cfg, tmp)
    os.replace(tmp, out / "config_resolved.yaml")


def write_stats(path: Path, records: list[FrameRecord]) -> None:
    fields = [f.name for f in dataclasses.fields(FrameRecord)]
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(fields)
        for r in records:
            w.writerow([getattr(r, f) for f in fields])
    tmp.replace(path)


def floor_summary(records: list[FrameRecord], T_base_cam: np.ndarray | None = None) -> dict:
    """What the run learnt about the floor: the keyframe steps the floor's region measured (``ground.road_region``)
    and the median of the measured step over the estimate's, how much the base rocked (median over keyframes of
    ``base_rocking_deg``, None when never judged), at how many keyframes floor points were tied to the floor in
    a level frame because of it, the floor's tilt in the base frame at the end (None: too few floor fits), at how
    many keyframes the learnt normal was used, and ``T_base_cam`` corrected by that tilt (when given)."""
    rocking = [rec.base_rocking_deg for rec in records if rec.is_keyframe and np.isfinite(rec.base_rocking_deg)]
    tilts = [(rec.floor_tilt_x_deg, rec.floor_tilt_y_deg, rec.floor_tilt_se_deg) for rec in records
             if rec.is_keyframe and np.isfinite(rec.floor_tilt_x_deg)]
    road = [rec.road_step_ratio for rec in records if rec.is_keyframe and np.isfinite(rec.road_step_ratio)]
    pitch = [rec.road_pitch_deg for rec in records if rec.is_keyframe and np.isfinite(rec.road_pitch_deg)]
    return {"road_region_steps": len(road),
            "road_region_ratio_median": round(float(np.median(road)), 5) if road else None,
            "road_region_pitch_deg_median": round(float(np.median(pitch)), 3) if pitch else None,
            "base_rocking_deg_median": round(float(np.median(rocking)), 4) if rocking else None,
            "level_frame_keyframes": sum(1 for rec in records if rec.level_frame),
            "floor_tilt_deg": None if not tilts else [round(float(v), 3) for v in tilts[-1][:2]],
            "floor_tilt_se_deg": None if not tilts else round(float(tilts[-1][2]), 3),
            "floor_normal_learnt_keyframes": sum(1 for rec in records if rec.floor_normal_learnt),
            "T_base_cam_levelled": None if not tilts or T_base_cam is None else [
                round(float(v), 6) for v in levelled_mount(T_base_cam, normal_from_tilt_deg(*tilts[-1][:2])).ravel()]}


def cue_summary(records: list[FrameRecord]) -> dict | None:
    """Floor against wheels over the run (``backend/cue_check.py``): the keyframes tested, the share that agreed,
    the median disagreement, and the disagreement the run ended in (its size and the frame it started at; None
    when the cues agreed at the end). None: never tested (no wheels, or no floor)."""
    tested = [rec for rec in records if rec.cues_agree is not None]
    if not tested:
        return None
    since = None
    for rec in reversed(tested):
        if rec.cues_agree:
            break
        since = rec
    return {"keyframes_tested": len(tested),
            "agreeing_share": round(sum(bool(rec.cues_agree) for rec in tested) / len(tested), 4),
            "disagreement_median": round(float(np.median([rec.cue_disagreement for rec in tested])), 5),
            "disagree_at_end": None if since is None else round(tested[-1].cue_disagreement, 5),
            "disagree_since_frame": None if since is None else since.frame_index}


def corners_spread_from_frame(records: list[FrameRecord]) -> int | None:
    """The frame at which the front end found the base rocking on its suspension and turned its detection to spread
    (``frontend/rocking.py``); None: it did not (no wheels, a level base, or a detection order set)."""
    return next((rec.frame_index for rec in records if ROCKING_NOTE in rec.note), None)


def slip_summary(records: list[FrameRecord]) -> dict | None:
    """Wheel steps judged on the window's solution (``backend/wheel_slip.py``): how many, how many were taken for
    slip and switched off, and the stretches of frames they span (first and last frame of each run of consecutive
    switched keyframes). None: no step judged (no wheels, or ``backend.odometry.slip_switch`` off)."""
    judged = [rec for rec in records if rec.wheel_slip is not None]
    if not judged:
        return None
    stretches: list[list[int]] = []
    previous = False
    for rec in judged:
        if rec.wheel_slip:
            if previous:
                stretches[-1][1] = rec.frame_index
            else:
                stretches.append([rec.frame_index, rec.frame_index])
        previous = bool(rec.wheel_slip)
    return {"keyframes_judged": len(judged), "switched_off": sum(bool(rec.wheel_slip) for rec in judged),
            "stretches": stretches}


def _slip_line(summary: dict) -> str | None:
    c = summary.get("wheel_slip")
    if c is None or not c["switched_off"]:
        return None
    spans = ", ".join(f"{a}-{b}" if a != b else f"{a}" for a, b in c["stretches"][:6])
    more = f" and {len(c['stretches']) - 6} more" if len(c["stretches"]) > 6 else ""
    return (f"wheel slip: {c['switched_off']} of {c['keyframes_judged']} wheel steps disagreed with the window's "
            f"solution and were switched off (frames {spans}{more})")


def _cue_line(summary: dict) -> str | None:
    c = summary.get("cue_check")
    if c is None:
        return None
    line = (f"floor against wheels: agree at {100 * c['agreeing_share']:.0f}% of {c['keyframes_tested']} keyframes "
            f"(median {100 * c['disagreement_median']:+.1f}%)")
    if c["disagree_at_end"] is not None:
        line += (f"; they disagree by {100 * c['disagree_at_end']:+.1f}% since frame {c['disagree_since_frame']} "
                 "(the floor's scale over the wheels': check backend.ground.camera_height_m / T_base_cam and the "
                 "wheels' scale)")
    return line


def _clock_dict(c) -> dict | None:
    if c is None:
        return None
    applied = c.applied_s is not None
    return {"offset_ms": round(1000.0 * c.offset_s, 2) if c.observable else None,
            "sigma_ms": round(1000.0 * c.sigma_s, 2) if c.observable else None,
            "observable": c.observable, "told_from_zero": c.zero_rejected, "intervals": c.n_intervals,
            "from_speed_changes": c.from_speed,
            "applied": applied,
            "applied_ms": round(1000.0 * c.applied_s, 2) if applied else None,
            "applied_since_s": round(c.applied_since_t, 3) if applied and c.applied_since_t is not None else None}


def _first_pass_dict(r: RunResult) -> dict | None:
    """A second pass's record of its first pass (``backend.odometry.time_offset_second_pass``)."""
    c = r.first_pass_clock
    if c is None:
        return None
    return {"offset_ms": 1000.0 * c.offset_s, "sigma_ms": round(1000.0 * c.sigma_s, 2),
            "applied_since_s": None if c.applied_since_t is None else round(c.applied_since_t, 3),
            "folder": FIRST_PASS_DIR}


def _clock_line(r: RunResult) -> str | None:
    c = r.wheel_time_offset
    if c is None:
        return None
    f = r.first_pass_clock
    if f is not None:
        since = "" if f.applied_since_t is None else f" from t={f.applied_since_t:.2f} s"
        done = ("interrupted: the first pass's complete results are" if r.interrupted else "the first pass's files")
        return (f"wheel clock: {1000.0 * f.offset_s:+.1f} ± {1000.0 * f.sigma_s:.1f} ms against the camera's, applied"
                f"{since} in a first pass; this is a second pass with the wheels read at that offset from the first "
                f"frame ({done} in {FIRST_PASS_DIR}/)")
    if c.applied_s is None:
        use = "not applied" if c.zero_rejected or not c.observable else "not applied (not told from a zero offset)"
    else:
        use = f"applied: wheels read at the camera's t {1000.0 * c.applied_s:+.1f} ms"
        if c.applied_since_t is not None:
            use += f" from t={c.applied_since_t:.2f} s"
    if not c.observable:
        return (f"wheel clock: offset to the camera not observable ({c.n_intervals} keyframe intervals; it shows in "
                f"turns and in speed changes); {use}")
    source = "the turns and the speed changes" if c.from_speed else "the turns"
    return (f"wheel clock: {1000.0 * c.offset_s:+.1f} ± {1000.0 * c.sigma_s:.1f} ms against the camera's "
            f"(estimated from {source}); {use}")


def summary_dict(report: JobReport, cfg: Config) -> dict:
    """The content of ``summary.json``."""
    r = report.result
    cal = r.wheel_calibration
    return {
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
        "floor_beside_track": r.floor_beside_track,
        "floor_depth_m": None if r.floor_depth_m is None else round(r.floor_depth_m, 4),
        "wheel_calibration": None if cal is None else {
            "scale": round(cal.scale, 5), "scale_sigma": round(cal.scale_sigma, 5),
            "yaw_bias_per_m": round(cal.yaw_bias_per_m, 6), "yaw_bias_sigma": round(cal.yaw_bias_sigma, 6),
            "yaw_scale": round(cal.yaw_scale, 5), "yaw_scale_sigma": round(cal.yaw_scale_sigma, 5)},
        "wheel_time_offset": _clock_dict(r.wheel_time_offset),
        "wheel_clock_first_pass": _first_pass_dict(r),
        "odometry_synthetic": bool(report.sequence.odometry is not None and report.sequence.odometry.synthetic),
        "interrupted": r.interrupted,
        **floor_summary(r.records, report.sequence.camera.T_base_cam),
        "cue_check": cue_summary(r.records),
        "wheel_slip": slip_summary(r.records),
        "corners_spread_from_frame": corners_spread_from_frame(r.records),
        "accuracy": report.accuracy.as_dict() if report.accuracy is not None else None,
        "accuracy_online": report.online_accuracy.as_dict() if report.online_accuracy is not None else None,
        "wheel_only_accuracy": report.wheel_accuracy.as_dict() if report.wheel_accuracy is not None else None,
    }


def write_summary(summary: dict, out: Path) -> None:
    """``summary.json``, atomically (temporary file, then rename): a stop while writing never leaves half of it."""
    with section(Stage.OUTPUTS):
        tmp = out / "summary.json.tmp"
        tmp.write_text(json.dumps(summary, indent=2, default=_plain))
        os.replace(tmp, out / "summary.json")


def _plain(value):
    """NumPy scalars and arrays as JSON's own types: a value computed with NumPy never costs a run its summary."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} in summary.json")


def _scale_line(r: RunResult, summary: dict) -> str:
    if not r.metric:
        return "monocular run (no wheel odometry, no floor at the camera height): the trajectory is up to scale"
    synthetic = " (wheels synthetic, see odometry.csv header)" if summary["odometry_synthetic"] else ""
    late = (f", from frame {r.metric_from_frame} on (the floor came into view there; the trajectory before it "
            f"is rescaled)" if r.metric_from_frame is not None else "")
    n_re = r.floor_scale_reanchors
    drift = f"; the floor taken back after a scale drift at {n_re} keyframe{'s' * (n_re != 1)}" if n_re else ""
    return "metric scale from: " + ", ".join(r.scale_sources) + synthetic + late + drift


def _floor_line(r: RunResult, summary: dict) -> str | None:
    floor = []
    if summary["road_region_steps"]:
        pitch = summary.get("road_region_pitch_deg_median")
        on = f", on the floor pitched {pitch:+.2f} deg from the set-up's (median)" if pitch else ""
        floor.append(f"its region measured {summary['road_region_steps']} keyframe steps (median "
                     f"{summary['road_region_ratio_median']:.3f} of the estimate's step{on}; backend.ground.road_region)")
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
    if r.floor_depth_m is not None:
        floor.append(f"estimated {r.floor_depth_m * 100:+.1f} cm below its configured height "
                     f"(backend.ground.height_sigma_fraction)")
    if r.floor_untied:
        if r.floor_beside_track:
            floor.append(f"{r.floor_untied} floor landmarks untied in later views: {r.floor_beside_track} beside the "
                         f"base's track (backend.ground.corridor_heights), {r.floor_untied - r.floor_beside_track} off "
                         f"the floor's heights (backend.ground.untie_sigmas)")
        else:
            floor.append(f"{r.floor_untied} floor landmarks found off it in later views and untied (a kerb or mat "
                         f"beside it; backend.ground.untie_sigmas)")
    return "floor: " + "; ".join(floor) if floor else None


def summary_lines(report: JobReport, summary: dict, out: Path) -> list[str]:
    """The console summary of a run (one line per topic)."""
    r = report.result
    lines = [f"windowvo: {r.n_frames} frames ({r.n_skipped} skipped), {r.n_keyframes} keyframes, "
             f"{r.wall_s:.1f} s, {r.fps:.1f} fps" + (" [interrupted]" if r.interrupted else ""), _scale_line(r, summary)]
    if r.wheel_calibration is not None:
        c = r.wheel_calibration
        lines.append(f"wheel calibration: scale {c.scale:.4f} ± {c.scale_sigma:.4f}, "
                     f"yaw bias {c.yaw_bias_per_m * 1000:.2f} ± {c.yaw_bias_sigma * 1000:.2f} mrad/m, "
                     f"yaw scale {c.yaw_scale:.4f} ± {c.yaw_scale_sigma:.4f}")
    clock = _clock_line(r)
    if clock is not None:
        lines.append(clock)
    floor = _floor_line(r, summary)
    if floor is not None:
        lines.append(floor)
    cues = _cue_line(summary)
    if cues is not None:
        lines.append(cues)
    slip = _slip_line(summary)
    if slip is not None:
        lines.append(slip)
    if report.accuracy is not None:
        lines.append("accuracy (smoothed): " + report.accuracy.summary(metric=r.metric))
    if report.online_accuracy is not None:
        lines.append("accuracy (causal, online): " + report.online_accuracy.summary(metric=r.metric))
    if report.wheel_accuracy is not None:
        lines.append(f"wheel odometry alone: ATE SE(3) {report.wheel_accuracy.ate_se3_rmse_m:.3f} m")
    lines.append(f"outputs: {out}")
    return lines
