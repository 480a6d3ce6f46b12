"""Trajectory accuracy built on ``evo``: ATE (SE(3) and Sim(3) alignment), RPE per metre, end drift.

Pure functions of two :class:`~windowvo.io.trajectory.Trajectory` objects; no files, no printing.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass

import numpy as np
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit

from ..errors import WindowVOError
from ..io.trajectory import Trajectory


@dataclass
class AccuracyReport:
    """Accuracy of one estimate against ground truth.

    For a monocular estimate (``monocular=True``) the translation is up to scale: the RPE and
    the end drift are computed on the estimate scaled by the Sim(3) alignment's scale (NaN when
    that scale cannot be estimated), and the ATE after SE(3) alignment is not reported.
    """

    n_poses: int
    path_length_m: float
    ate_se3_rmse_m: float  # meaningless (arbitrary unit) when monocular
    ate_sim3_rmse_m: float
    sim3_scale: float  # scale that maps the estimate onto the ground truth
    rpe_trans_per_m: float  # RMSE of the translation error over 1 m segments (m); Sim(3)-scaled when monocular
    end_drift_pct: float  # end-point error after aligning the first pose, % of path length; Sim(3)-scaled when monocular
    monocular: bool = False

    def as_dict(self) -> dict:
        """JSON-ready: NaN becomes None, and so does the ATE SE(3) of a monocular estimate."""
        d: dict = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}
        if self.monocular:
            d["ate_se3_rmse_m"] = None
        return d

    def summary(self, metric: bool | None = None) -> str:
        """One line. ``metric=False`` marks the estimate as up to scale; it defaults to ``not monocular``.

        Numbers in an arbitrary scale are never printed: a monocular report shows RPE and end drift
        after the Sim(3) scale, and a report computed as metric but shown as monocular omits them.
        """
        metric = not self.monocular if metric is None else metric
        head = f"ATE SE(3) {self.ate_se3_rmse_m:.3f} m" if metric else "ATE SE(3) n/a (monocular, up to scale)"
        sim3 = f"ATE Sim(3) {self.ate_sim3_rmse_m:.3f} m (scale {self.sim3_scale:.3f})"
        if metric:
            rel = (f"RPE {self.rpe_trans_per_m:.3f} m per m | end drift {self.end_drift_pct:.2f}% of "
                   f"{self.path_length_m:.1f} m")
        elif self.monocular and math.isfinite(self.sim3_scale):
            rel = (f"RPE {self.rpe_trans_per_m:.3f} m per m after Sim(3) scale | end drift "
                   f"{self.end_drift_pct:.2f}% of {self.path_length_m:.1f} m after Sim(3) scale")
        else:
            rel = "RPE and end drift n/a (scale unknown)"
        return f"{head} | {sim3} | {rel}"


def _to_evo(traj: Trajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=[T.copy() for T in traj.T_world_base], timestamps=traj.timestamps.copy())


def _associate_evo(groundtruth: Trajectory, estimate: Trajectory,
                   max_time_diff: float) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    try:
        return evo_sync.associate_trajectories(_to_evo(groundtruth), _to_evo(estimate), max_diff=max_time_diff)
    except Exception as err:  # evo raises its own SyncException
        raise WindowVOError(f"cannot associate estimate with ground truth: {err}") from None


def associate(groundtruth: Trajectory, estimate: Trajectory,
              max_time_diff: float = 0.02) -> tuple[Trajectory, Trajectory]:
    """The poses of both trajectories matched by timestamp (evo's association, as :func:`evaluate`
    uses): two trajectories of equal length, pose i of one matched with pose i of the other.
    Raises :class:`WindowVOError` when nothing matches."""
    ref, est = _associate_evo(groundtruth, estimate, max_time_diff)
    return (Trajectory(np.asarray(ref.timestamps, float), np.stack(ref.poses_se3)),
            Trajectory(np.asarray(est.timestamps, float), np.stack(est.poses_se3)))


def evaluate(groundtruth: Trajectory, estimate: Trajectory, max_time_diff: float = 0.02, *,
             monocular: bool = False) -> AccuracyReport:
    """Accuracy of ``estimate`` against ``groundtruth`` (both ``T_world_base``).

    ``monocular``: the estimate is up to scale, so RPE and end drift are measured after
    applying the Sim(3) alignment's scale (see :class:`AccuracyReport`).
    """
    ref, est = _associate_evo(groundtruth, estimate, max_time_diff)
    if ref.num_poses < 3:
        raise WindowVOError("fewer than 3 poses in common between estimate and ground truth")
    path_len = float(ref.path_length)

    def ate(correct_scale: bool) -> tuple[float, float, PoseTrajectory3D]:
        e = copy.deepcopy(est)
        try:
            _, _, s = e.align(ref, correct_scale=correct_scale)
        except GeometryException:
            # Degenerate ground-truth geometry (a straight line, a spin in place): Umeyama has no
            # unique answer, so align the first poses instead and leave the scale alone.
            e.align_origin(ref)
            s = float("nan") if correct_scale else 1.0
        m = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        m.process_data((ref, e))
        return float(m.get_statistic(evo_metrics.StatisticsType.rmse)), float(s), e

    ate_se3, _, _ = ate(False)
    ate_sim3, scale, est_sim3 = ate(True)
    # RPE and end drift do not depend on a rigid alignment, but they do on the scale: a
    # monocular estimate is measured in the Sim(3) scale, or not at all.
    est_rel = est
    if monocular:
        est_rel = est_sim3 if math.isfinite(scale) else None
    rpe = float("nan")
    drift = float("nan")
    if est_rel is not None:
        if path_len > 2.0:
            try:
                # Segments of 1 m of the *ground truth* path: evo picks them on the estimate by
                # default, which for a mis-scaled estimate are not metres at all.
                m = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, delta=1.0, delta_unit=Unit.meters,
                                    all_pairs=False, pairs_from_reference=True)
                m.process_data((ref, est_rel))
                rpe = float(m.get_statistic(evo_metrics.StatisticsType.rmse))
            except Exception:
                rpe = float("nan")
        e0 = copy.deepcopy(est_rel)
        e0.align_origin(ref)
        end_err = float(np.linalg.norm(e0.positions_xyz[-1] - ref.positions_xyz[-1]))
        drift = 100.0 * end_err / path_len if path_len > 0 else float("nan")
    return AccuracyReport(ref.num_poses, path_len, ate_se3, ate_sim3, scale, rpe, drift, monocular)


def plot_trajectories(path, groundtruth: Trajectory | None, estimates: dict[str, Trajectory], title: str = "") -> None:
    """Top-down (x-y) plot of trajectories, ground truth first, written as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 5.6), dpi=110)
    if groundtruth is not None:
        g = groundtruth.anchored().positions
        ax.plot(g[:, 0], g[:, 1], "k--", lw=1.5, label="ground truth")
    for name, tr in estimates.items():
        p = tr.anchored().positions
        ax.plot(p[:, 0], p[:, 1], lw=1.3, label=name)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
