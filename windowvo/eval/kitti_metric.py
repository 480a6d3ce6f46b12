"""The KITTI odometry benchmark's relative error (devkit ``evaluate_odometry.cpp``), as pure functions.

Definition (the devkit's ``calcSequenceErrors``), on poses matched frame by frame:

* ``dist[i]``: distance driven along the *ground truth* from frame 0 to frame i (sum of the
  straight steps between consecutive positions).
* first frames 0, 10, 20, ... (``step_size = 10``, one second at KITTI's 10 Hz);
* for each first frame and each segment length ``L``, the last frame is the **first** frame i
  (i >= first) with ``dist[i] > dist[first] + L`` (strictly); no such frame: no segment;
* ``pose_error = inv(inv(est[first]) est[last]) (inv(gt[first]) gt[last])`` (the devkit's order;
  its inverse has the same translation norm and rotation angle);
* ``t_err = |t(pose_error)| / L`` and ``r_err = acos(max(min(0.5 (trace(R) - 1), 1), -1)) / L``;
* the reported numbers are the means of ``t_err`` and ``r_err`` over all segments of all lengths
  (the devkit's ``saveStats``). Its ``stats.txt`` holds them as a fraction and rad/m, its plots in %
  and deg/m; here ``t_rel_pct`` is in % and ``r_rel_deg_per_100m`` in degrees per 100 m
  (``r_rel_deg_per_m`` gives the devkit plots' unit).

The devkit lengths are 100, 200, ..., 800 m; ``SegmentSet.SHORT`` (10, 20, ..., 80 m) applies the
same rule to recordings of tens of metres. Differences from the devkit: float64 instead of float32,
poses matched by timestamp (the devkit requires equal-length files), and the frame is whatever the
trajectories hold (windowvo's ``T_world_base``; pass ``T_base_frame`` to measure another rigidly
attached frame, e.g. KITTI's camera 0, as the devkit does).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from ..io.trajectory import Trajectory
from .metrics import associate

DEVKIT_STEP_FRAMES = 10


class SegmentSet(enum.Enum):
    """Which segment lengths: the devkit's 100-800 m, or 10-80 m for short recordings."""

    DEVKIT = "devkit"
    SHORT = "short"

    @property
    def lengths_m(self) -> tuple[float, ...]:
        step = 100.0 if self is SegmentSet.DEVKIT else 10.0
        return tuple(step * k for k in range(1, 9))

    @property
    def label(self) -> str:
        return "KITTI devkit segments 100-800 m" if self is SegmentSet.DEVKIT else "short segments 10-80 m"


@dataclass(frozen=True)
class SegmentError:
    """One segment, in the devkit's units (its ``errors`` struct without the speed)."""

    first_frame: int
    last_frame: int
    length_m: float
    t_err: float  # |translation of the error pose| / length (a fraction)
    r_err_rad_per_m: float  # rotation angle of the error pose / length


@dataclass(frozen=True)
class LengthError:
    """Mean error of the segments of one length (the devkit's per-length plot needs n_segments >= 3)."""

    n_segments: int
    t_rel_pct: float
    r_rel_deg_per_100m: float


@dataclass(frozen=True)
class KittiOdometryError:
    """Mean KITTI relative error over all segments; ``None`` and ``n_segments == 0`` when the
    ground truth is too short for any segment."""

    label: str
    lengths_m: tuple[float, ...]
    step_frames: int
    n_segments: int
    t_rel_pct: float | None  # mean t_err, in %
    r_rel_deg_per_100m: float | None  # mean r_err, in degrees per 100 m
    per_length: dict[float, LengthError]  # only the lengths that have segments
    gt_path_length_m: float  # of the matched ground-truth poses
    estimate_scale: float = 1.0  # the estimate's translations were multiplied by it (monocular: Sim(3) scale)

    @property
    def r_rel_deg_per_m(self) -> float | None:
        """The devkit plots' unit."""
        return None if self.r_rel_deg_per_100m is None else self.r_rel_deg_per_100m / 100.0

    def as_dict(self) -> dict:
        return {"label": self.label, "lengths_m": list(self.lengths_m), "step_frames": self.step_frames,
                "n_segments": self.n_segments, "t_rel_pct": self.t_rel_pct,
                "r_rel_deg_per_100m": self.r_rel_deg_per_100m, "gt_path_length_m": self.gt_path_length_m,
                "estimate_scale": self.estimate_scale,
                "per_length": {f"{k:g}": {"n_segments": v.n_segments, "t_rel_pct": v.t_rel_pct,
                                          "r_rel_deg_per_100m": v.r_rel_deg_per_100m}
                               for k, v in self.per_length.items()}}

    def summary(self) -> str:
        """One line, e.g. ``short segments 10-80 m: t_rel 2.00 % | r_rel 0.000 deg/100 m ...``."""
        if self.n_segments == 0 or self.t_rel_pct is None or self.r_rel_deg_per_100m is None:
            return (f"{self.label}: n/a (ground-truth path {self.gt_path_length_m:.1f} m, no segment longer "
                    f"than {min(self.lengths_m):g} m)")
        scaled = "" if self.estimate_scale == 1.0 else f" | estimate scaled by {self.estimate_scale:.4f} (Sim(3))"
        return (f"{self.label}: t_rel {self.t_rel_pct:.2f} % | r_rel {self.r_rel_deg_per_100m:.3f} deg/100 m "
                f"({self.r_rel_deg_per_100m / 100.0:.5f} deg/m) | {self.n_segments} segments{scaled}")


def trajectory_distances(positions: np.ndarray) -> np.ndarray:
    """Distance driven from the first position to each one (the devkit's ``trajectoryDistances``)."""
    p = np.asarray(positions, float).reshape(-1, 3)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def last_frame_from_segment_length(dist: np.ndarray, first_frame: int, length_m: float) -> int | None:
    """The first frame i >= first_frame with ``dist[i] > dist[first_frame] + length_m``, or None
    (the devkit's ``lastFrameFromSegmentLength``; ``dist`` is non-decreasing)."""
    i = int(np.searchsorted(dist, dist[first_frame] + length_m, side="right"))
    return max(i, first_frame) if i < len(dist) else None


def rotation_error_rad(T_error: np.ndarray) -> float:
    """Rotation angle of a pose error, as the devkit clamps it."""
    d = 0.5 * (float(np.trace(T_error[:3, :3])) - 1.0)
    return math.acos(max(min(d, 1.0), -1.0))


def segment_errors(T_gt: np.ndarray, T_est: np.ndarray, lengths_m: tuple[float, ...],
                   step_frames: int = DEVKIT_STEP_FRAMES) -> list[SegmentError]:
    """The devkit's ``calcSequenceErrors`` on two (N, 4, 4) pose arrays matched index by index."""
    if len(T_gt) != len(T_est):
        raise ValueError(f"{len(T_gt)} ground-truth poses but {len(T_est)} estimated")
    if step_frames < 1:
        raise ValueError(f"step_frames must be >= 1, got {step_frames}")
    dist = trajectory_distances(T_gt[:, :3, 3]) if len(T_gt) else np.zeros(0)
    out: list[SegmentError] = []
    for first in range(0, len(T_gt), step_frames):
        for length in lengths_m:
            last = last_frame_from_segment_length(dist, first, length)
            if last is None:
                continue
            # general inverses, as the devkit's Matrix::inv (exact for slightly non-orthonormal input)
            delta_gt = np.linalg.inv(T_gt[first]) @ T_gt[last]
            delta_est = np.linalg.inv(T_est[first]) @ T_est[last]
            T_error = np.linalg.inv(delta_est) @ delta_gt
            out.append(SegmentError(first, last, float(length), float(np.linalg.norm(T_error[:3, 3])) / length,
                                    rotation_error_rad(T_error) / length))
    return out


def summarize_segments(errors: list[SegmentError], lengths_m: tuple[float, ...], label: str, *,
                       step_frames: int = DEVKIT_STEP_FRAMES, gt_path_length_m: float = float("nan"),
                       estimate_scale: float = 1.0) -> KittiOdometryError:
    """Means over all segments (the devkit's ``saveStats``) and per length, in % and deg/100 m."""
    def pct(es: list[SegmentError]) -> float:
        return 100.0 * float(np.mean([e.t_err for e in es]))

    def deg100(es: list[SegmentError]) -> float:
        return 100.0 * math.degrees(float(np.mean([e.r_err_rad_per_m for e in es])))

    per_length: dict[float, LengthError] = {}
    for length in lengths_m:
        es = [e for e in errors if e.length_m == float(length)]
        if es:
            per_length[float(length)] = LengthError(len(es), pct(es), deg100(es))
    t_rel = pct(errors) if errors else None
    r_rel = deg100(errors) if errors else None
    return KittiOdometryError(label, tuple(float(x) for x in lengths_m), step_frames, len(errors), t_rel, r_rel,
                              per_length, float(gt_path_length_m), float(estimate_scale))


def kitti_odometry_error(groundtruth: Trajectory, estimate: Trajectory, segments: SegmentSet = SegmentSet.DEVKIT,
                         *, max_time_diff: float = 0.02, step_frames: int = DEVKIT_STEP_FRAMES,
                         estimate_scale: float = 1.0, T_base_frame: np.ndarray | None = None) -> KittiOdometryError:
    """KITTI relative error of ``estimate`` against ``groundtruth`` (both ``T_world_base``).

    Poses are matched by timestamp as :func:`~windowvo.eval.metrics.evaluate` does (raises
    :class:`~windowvo.errors.WindowVOError` when none match); frames are counted on the matched
    poses. ``estimate_scale`` multiplies the estimate's translations (a monocular estimate's Sim(3)
    scale). ``T_base_frame`` measures the frame ``T_world_base @ T_base_frame`` instead of the base
    (e.g. ``kitti_T_base_cam0()`` for the devkit's camera-0 numbers). A ground truth too short for
    any segment gives ``n_segments == 0`` and ``None`` errors."""
    gt, est = associate(groundtruth, estimate, max_time_diff)
    T_gt, T_est = gt.T_world_base.copy(), est.T_world_base.copy()
    T_est[:, :3, 3] *= estimate_scale
    if T_base_frame is not None:
        T_gt, T_est = T_gt @ T_base_frame, T_est @ T_base_frame
    errors = segment_errors(T_gt, T_est, segments.lengths_m, step_frames)
    path = float(trajectory_distances(T_gt[:, :3, 3])[-1])
    return summarize_segments(errors, segments.lengths_m, segments.label, step_frames=step_frames,
                              gt_path_length_m=path, estimate_scale=estimate_scale)
