"""The wheel odometry's clock against the camera's: the time offset, estimated online from the turns.

Sensors stamped by different drivers disagree about time by a few to tens of milliseconds; at speed v an
offset dt is a position error of v * dt at every keyframe, and in turns a heading error. The heading change
the wheels report between two keyframes, read at the keyframe times shifted by ``dt``, must match the one
vision measured (the front end's two-view rotation, no wheels in it), up to the wheels' yaw scale (track
width) and yaw bias per metre. So for each candidate ``dt`` on a grid the wheel heading changes are fitted
linearly to vision's (``a * vision + b * distance``), and the offset is the ``dt`` of the smallest residual,
refined by a parabola through its neighbours. Its standard error comes from the residual's curvature, widened
by how much the intervals overlap (overlapping intervals share the wheels' heading noise: they are not independent).

What limits it: the wheels' heading random walk (``sigma_w`` rad/sqrt(m) at speed ``v``) allows no estimator a
standard error below ``sqrt(sigma_w**2 * v / integral(yaw''(t)**2 dt))``: the offset only shows where the turn
rate changes. On a rendered 15-20 s figure eight (0.002 rad/sqrt(m), 0.8 m/s) that is 2-3 ms; a constant-rate
circle does not show it at all.

A path without turns (a straight road) does not show the offset: the estimate then says so
(``observable`` False) and the offset stays at its last observable value (zero at the start).
Convention: ``t_wheels = t_camera + offset_s``: the wheel sample stamped ``t + offset_s`` describes the
instant the camera stamped ``t``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..io.odometry import WheelOdometry

# Offsets searched (s) and the grid step.
MAX_OFFSET_S = 0.1
GRID_STEP_S = 0.001
# Keyframe intervals remembered, and what they must hold before an estimate is made: enough of them, and enough
# change of turn rate between them (a constant turn rate shows no offset either).
WINDOW_INTERVALS = 80
MIN_INTERVALS = 15
MIN_TURN_VARIATION_RAD = 0.05
# An estimate is used only when its standard error is below this (s).
MAX_SIGMA_S = 0.004
# ... and when the fit at the estimate beats the fit at a zero offset by a likelihood-ratio test: the drop of the
# residual sum of squares, in residual variances (counted by the intervals' overlap), above the chi-square quantile
# of 1 degree of freedom at 99%. The curvature's sigma is local: it cannot see a second minimum near zero.
CHI2_1DOF_99 = 6.635


@dataclass(frozen=True)
class ClockEstimate:
    """The wheels' time offset to the camera's clock (``t_wheels = t_camera + offset_s``)."""

    offset_s: float = 0.0
    sigma_s: float = float("nan")
    observable: bool = False  # enough turning to tell the offset
    n_intervals: int = 0
    zero_rejected: bool = False  # the data tell this offset from none (likelihood-ratio test at 99%)
    # The offset applied to the wheel readings when the run ended (None: none was) and the camera time from which
    # one was (``Odometry``; the estimate alone leaves both None).
    applied_s: float | None = None
    applied_since_t: float | None = None


@dataclass(frozen=True)
class _Interval:
    t0: float
    t1: float
    vision_yaw_rad: float  # heading change of the base from t0 to t1, from vision alone


class WheelClock:
    """Collects keyframe intervals with vision's heading change and estimates the wheels' time offset."""

    def __init__(self, max_offset_s: float = MAX_OFFSET_S, window: int = WINDOW_INTERVALS):
        self.max_offset_s = max_offset_s
        self.intervals: deque[_Interval] = deque(maxlen=window)
        self.estimate = ClockEstimate()
        self.n_added = 0  # intervals added so far (the window may have dropped the oldest)

    def add(self, t0: float, t1: float, vision_yaw_rad: float) -> None:
        """One keyframe interval and the base's heading change over it as vision measured it."""
        if t1 > t0 and np.isfinite(vision_yaw_rad):
            self.intervals.append(_Interval(float(t0), float(t1), float(vision_yaw_rad)))
            self.n_added += 1

    def update(self, wheels: WheelOdometry) -> ClockEstimate:
        """Re-estimate from the intervals so far; keeps the last observable estimate when this one is not."""
        est = estimate_offset(list(self.intervals), wheels, self.max_offset_s)
        if est.observable:
            self.estimate = est
        else:
            self.estimate = ClockEstimate(self.estimate.offset_s, self.estimate.sigma_s, self.estimate.observable,
                                          est.n_intervals, self.estimate.zero_rejected)
        return self.estimate


def _residuals(t0: np.ndarray, t1: np.ndarray, vis: np.ndarray, wheels: WheelOdometry,
               offsets: np.ndarray) -> np.ndarray:
    """Residual sum of squares of the linear fit wheel heading change ~ a * vision + b * distance, per offset."""
    ts, yaw = wheels.timestamps, wheels.yaw
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(wheels.x), np.diff(wheels.y)))])
    rss = np.empty(len(offsets))
    for i, dt in enumerate(offsets):
        dyaw = np.interp(t1 + dt, ts, yaw) - np.interp(t0 + dt, ts, yaw)
        dist = np.interp(t1 + dt, ts, s) - np.interp(t0 + dt, ts, s)
        A = np.column_stack([vis, dist])
        coef, *_ = np.linalg.lstsq(A, dyaw, rcond=None)
        rss[i] = float(np.sum((dyaw - A @ coef) ** 2))
    return rss


def _overlap(t0: np.ndarray, t1: np.ndarray) -> float:
    """How many intervals cover an instant of their union, on average (1 for intervals that do not overlap)."""
    order = np.argsort(t0)
    a, b = t0[order], t1[order]
    union, end = 0.0, -np.inf
    for lo, hi in zip(a, b):
        union += max(hi - max(lo, end), 0.0)
        end = max(end, hi)
    return max(float(np.sum(t1 - t0)) / union, 1.0) if union > 0 else 1.0


def estimate_offset(intervals: list[_Interval], wheels: WheelOdometry,
                    max_offset_s: float = MAX_OFFSET_S) -> ClockEstimate:
    """The offset that best explains the wheels' heading changes by vision's (see the module docstring)."""
    n = len(intervals)
    if n < MIN_INTERVALS:
        return ClockEstimate(n_intervals=n)
    t0 = np.array([iv.t0 for iv in intervals])
    t1 = np.array([iv.t1 for iv in intervals])
    vis = np.array([iv.vision_yaw_rad for iv in intervals])
    # Keep the intervals whose shifted times the wheels cover at every offset of the grid.
    inside = (t0 - max_offset_s >= wheels.timestamps[0]) & (t1 + max_offset_s <= wheels.timestamps[-1])
    t0, t1, vis = t0[inside], t1[inside], vis[inside]
    rate = vis / (t1 - t0)
    if len(vis) < MIN_INTERVALS or float(np.ptp(rate * np.median(t1 - t0))) < MIN_TURN_VARIATION_RAD:
        return ClockEstimate(n_intervals=len(vis))
    offsets = np.arange(-max_offset_s, max_offset_s + GRID_STEP_S / 2, GRID_STEP_S)
    rss = _residuals(t0, t1, vis, wheels, offsets)
    i = int(np.argmin(rss))
    if i == 0 or i == len(offsets) - 1:  # at the edge of the search: no minimum inside it
        return ClockEstimate(n_intervals=len(vis))
    r_m, r_0, r_p = rss[i - 1], rss[i], rss[i + 1]
    curvature = (r_p - 2.0 * r_0 + r_m) / GRID_STEP_S**2
    if not curvature > 0:
        return ClockEstimate(n_intervals=len(vis))
    shift = 0.5 * (r_m - r_p) / (r_p - 2.0 * r_0 + r_m) * GRID_STEP_S
    offset = float(offsets[i] + np.clip(shift, -GRID_STEP_S, GRID_STEP_S))
    # Gauss-Newton: var(dt) = 2 sigma^2 / RSS''(dt), with sigma^2 the residual variance of the fit; times the
    # intervals' overlap (each instant covered by that many of them on average), as they are not independent.
    sigma2 = r_0 / max(len(vis) - 3, 1)
    overlap = _overlap(t0, t1)
    sigma_s = float(np.sqrt(2.0 * sigma2 / curvature * overlap))
    rss_zero = float(rss[int(np.argmin(np.abs(offsets)))])
    zero_rejected = bool((rss_zero - r_0) / max(sigma2 * overlap, 1e-300) > CHI2_1DOF_99)
    return ClockEstimate(offset, sigma_s, sigma_s <= MAX_SIGMA_S, len(vis), zero_rejected)
