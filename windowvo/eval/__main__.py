"""``python -m windowvo.eval GROUNDTRUTH ESTIMATE [--plot out.png]``: accuracy of a trajectory.

Reads TUM files (windowvo's outputs) and KITTI ``poses.txt`` files, detected from the column count.
"""

from __future__ import annotations

import argparse
import enum
import json
import math
import os
import sys
from pathlib import Path

from ..errors import SequenceError, WindowVOError, cli_error
from ..io.trajectory import (
    KITTI_DEFAULT_DT_S,
    LoadedTrajectory,
    TimesSource,
    TrajectoryFormat,
    kitti_T_base_cam0,
    read_text_lenient,
    read_trajectory,
)
from .kitti_metric import KittiOdometryError, SegmentSet, kitti_odometry_error
from .metrics import AccuracyReport, evaluate, plot_trajectories

PROG = "windowvo.eval"
UP_TO_SCALE_MARK = "up to scale"  # windowvo writes it into a monocular trajectory's header
AUTO = "auto"


class KittiFrame(enum.Enum):
    """The frame whose poses the KITTI metric measures."""

    BASE = "base"  # windowvo's T_world_base
    CAM0 = "cam0"  # KITTI camera 0 (T_world_base @ T_base_cam0), as the devkit measures KITTI poses


def says_up_to_scale(path: Path) -> bool:
    """True when the TUM file's comment lines say the trajectory is up to scale."""
    try:
        text = read_text_lenient(Path(path))
    except WindowVOError:
        return False
    for line in text.splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            return False
        if UP_TO_SCALE_MARK in s:
            return True
    return False


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m windowvo.eval", description="ATE (SE(3) and Sim(3)), RPE per metre, "
                                "end drift and the KITTI odometry relative error (t_rel %%, r_rel deg/100 m; devkit "
                                "segments 100-800 m and short segments 10-80 m) of an estimate against ground truth. "
                                "Files: TUM (8 numbers a line, windowvo's outputs) or KITTI poses.txt (12 numbers, a "
                                "camera-0 pose; times from a times.txt beside it, else frame index x --kitti-dt), "
                                "detected automatically. A monocular estimate (its header says 'up to scale', or "
                                "--monocular) is measured after the Sim(3) scale, and gets no ATE SE(3).")
    p.add_argument("groundtruth")
    p.add_argument("estimate")
    p.add_argument("--plot", help="write a top-down PNG plot here")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--max-time-diff", type=float, default=0.02, help="s, for associating poses")
    formats = [AUTO] + [f.value for f in TrajectoryFormat]
    p.add_argument("--gt-format", choices=formats, default=AUTO, help="ground-truth file format (default: detect)")
    p.add_argument("--est-format", choices=formats, default=AUTO, help="estimate file format (default: detect)")
    p.add_argument("--kitti-dt", type=float, default=KITTI_DEFAULT_DT_S,
                   help="s between KITTI poses when no times.txt lies beside the file (default 0.1, 10 Hz)")
    p.add_argument("--kitti-frame", choices=[f.value for f in KittiFrame], default=KittiFrame.BASE.value,
                   help="frame the KITTI metric measures: windowvo's base (default) or KITTI camera 0 "
                        "(1.65 m above the base, the devkit's frame for KITTI poses)")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--monocular", action="store_true", help="the estimate is up to scale")
    scale.add_argument("--metric", action="store_true", help="the estimate is metric, whatever its header says")
    return p


def _read(path: str, fmt: str, dt: float) -> LoadedTrajectory:
    return read_trajectory(Path(path), None if fmt == AUTO else TrajectoryFormat(fmt), kitti_dt_s=dt)


def _check_plot_path(plot: str | None) -> None:
    if plot and not Path(plot).resolve().parent.is_dir():
        raise SequenceError(f"--plot: directory not found: {Path(plot).parent}")


def _kitti(gt: LoadedTrajectory, est: LoadedTrajectory, rep: AccuracyReport, a: argparse.Namespace,
           ) -> dict[SegmentSet, KittiOdometryError | None]:
    """Both KITTI metrics; None when a monocular estimate's scale is unknown."""
    scale = rep.sim3_scale if rep.monocular else 1.0
    if not math.isfinite(scale):
        return {s: None for s in SegmentSet}
    T_bf = kitti_T_base_cam0() if KittiFrame(a.kitti_frame) is KittiFrame.CAM0 else None
    return {s: kitti_odometry_error(gt.trajectory, est.trajectory, s, max_time_diff=a.max_time_diff,
                                    estimate_scale=scale, T_base_frame=T_bf) for s in SegmentSet}


def _text(gt: LoadedTrajectory, est: LoadedTrajectory, rep: AccuracyReport,
          kitti: dict[SegmentSet, KittiOdometryError | None], frame: KittiFrame) -> str:
    lines = [f"ground truth: {gt.describe()}", f"estimate: {est.describe()}", rep.summary()]
    where = "" if frame is KittiFrame.BASE else " (camera 0 poses)"
    for s, k in kitti.items():
        line = k.summary() if k is not None else f"{s.label}: n/a (monocular, scale unknown)"
        lines.append(line.replace(s.label, s.label + where, 1))
    return "\n".join(lines)


def _json(gt: LoadedTrajectory, est: LoadedTrajectory, rep: AccuracyReport,
          kitti: dict[SegmentSet, KittiOdometryError | None], frame: KittiFrame) -> str:
    d = rep.as_dict()
    d["groundtruth_read"] = gt.describe()
    d["estimate_read"] = est.describe()
    d["kitti_frame"] = frame.value
    for s, k in kitti.items():
        d[f"kitti_{s.value}"] = None if k is None else k.as_dict()
    return json.dumps(d, indent=2, allow_nan=False)


def _time_base_note(gt: LoadedTrajectory, est: LoadedTrajectory, n_matched: int) -> str | None:
    if n_matched >= min(len(gt.trajectory), len(est.trajectory)):
        return None
    if TimesSource.FRAME_INDEX in (gt.times, est.times) and gt.times is not est.times:
        return (f"{PROG}: note: only {n_matched} poses matched in time, and one file's times are frame index x "
                "--kitti-dt while the other's are real times (put the sequence's times.txt beside the KITTI file)")
    return None


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    try:
        _check_plot_path(a.plot)
        gt = _read(a.groundtruth, a.gt_format, a.kitti_dt)
        est = _read(a.estimate, a.est_format, a.kitti_dt)
        is_tum = est.format is TrajectoryFormat.TUM
        monocular = a.monocular or (not a.metric and is_tum and says_up_to_scale(a.estimate))
        rep = evaluate(gt.trajectory, est.trajectory, a.max_time_diff, monocular=monocular)
        kitti = _kitti(gt, est, rep, a)
    except WindowVOError as err:
        return cli_error(err, PROG)
    frame = KittiFrame(a.kitti_frame)
    note = _time_base_note(gt, est, rep.n_poses)
    if note:
        print(note, file=sys.stderr)
    try:
        print(_json(gt, est, rep, kitti, frame) if a.json else _text(gt, est, rep, kitti, frame), flush=True)
    except BrokenPipeError:  # piped into head: stop quietly (Python's documented recipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    if a.plot:
        try:
            plot_trajectories(a.plot, gt.trajectory, {"estimate": est.trajectory})
        except (OSError, ValueError) as err:
            msg = getattr(err, "strerror", None) or str(err).splitlines()[0]
            return cli_error(f"cannot write the plot {a.plot}: {msg}", PROG)
    return 0


if __name__ == "__main__":
    sys.exit(main())
