"""Wheel odometry synthesised from ground truth (datasets without wheels, such as KITTI, and the
renderer): planar increments of the base with a scale error, a yaw bias per metre, noise and slip."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .odometry import WheelOdometry
from .trajectory import Trajectory


def integrate_wheel_odometry(ts: np.ndarray, ds: np.ndarray, dyaw: np.ndarray, *, scale_error: float,
                             yaw_bias_per_m: float, distance_noise: float, yaw_noise: float,
                             rng: np.random.Generator, slip_windows: Iterable[tuple[float, float, float]] = (),
                             comment: str = "") -> WheelOdometry:
    """Dead-reckon wheel odometry from the true planar increments of the base.

    ``ds[i]`` (signed distance along the base's x axis) and ``dyaw[i]`` are the true motion from
    ``ts[i-1]`` to ``ts[i]`` (entry 0 is unused). What the wheels report: the distance scaled by
    ``1 + scale_error`` (and by ``1 + extra`` inside each slip window ``(t0, t1, extra)``) plus a
    random walk of ``distance_noise`` m/sqrt(m); the heading change plus ``yaw_bias_per_m`` rad
    per metre and a random walk of ``yaw_noise`` rad/sqrt(m). Integrated at the mid heading.
    """
    ts = np.asarray(ts, float)
    n = len(ts)
    ds = np.asarray(ds, float)[1:]
    dyaw = np.asarray(dyaw, float)[1:]
    factor = np.full(n - 1, 1.0 + scale_error)
    for t0, t1, extra in slip_windows:
        factor[(ts[1:] >= t0) & (ts[1:] <= t1)] *= 1.0 + extra
    dist = np.abs(ds)
    z = rng.standard_normal((n - 1, 2))  # per step: distance noise, then heading noise
    ds_m = ds * factor + distance_noise * np.sqrt(dist) * z[:, 0]
    dyaw_m = dyaw + yaw_bias_per_m * dist + yaw_noise * np.sqrt(dist) * z[:, 1]
    yaw = np.concatenate([[0.0], np.cumsum(dyaw_m)])
    mid = yaw[:-1] + 0.5 * dyaw_m
    x = np.concatenate([[0.0], np.cumsum(ds_m * np.cos(mid))])
    y = np.concatenate([[0.0], np.cumsum(ds_m * np.sin(mid))])
    return WheelOdometry(ts.copy(), x, y, yaw, comment=comment)


def synthesize_odometry(gt: Trajectory, scale_error: float, yaw_bias_per_m: float, noise: float, seed: int,
                        label: str) -> WheelOdometry:
    """Wheel odometry from ground truth: planar increments of the base with the generator's errors."""
    T = gt.T_world_base
    d = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, 3:] - T[:-1, :3, 3:])[:, :, 0]  # R_prev^T dt
    R_rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    ds = np.concatenate([[0.0], np.hypot(d[:, 0], d[:, 1]) * np.where(d[:, 0] >= 0, 1.0, -1.0)])
    dyaw = np.concatenate([[0.0], np.arctan2(R_rel[:, 1, 0], R_rel[:, 0, 0])])
    comment = (f"{label} wheel odometry synthesised from ground truth: scale_error={scale_error}, "
               f"yaw_bias_per_m={yaw_bias_per_m}, noise={noise}, seed={seed}")
    return integrate_wheel_odometry(gt.timestamps, ds, dyaw, scale_error=scale_error, yaw_bias_per_m=yaw_bias_per_m,
                                    distance_noise=noise, yaw_noise=noise, rng=np.random.default_rng(seed),
                                    comment=comment)
