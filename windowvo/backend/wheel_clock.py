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
circle does not show it at all, nor a circle driven stop-and-go (its turn rate changes with the speed alone: the
wheels' own distance term fits it at any offset, and a 40 s warehouse loop was put 30 ms off with a 3.6 ms sigma).

A path without turns (a straight road) does not show the offset: the estimate then says so
(``observable`` False) and the offset stays at its last observable value (zero at the start).
The speed tells it too, where the turns do not (a robot that stops and starts on a straight line): the image
moves by about ``gain * distance`` between two frames, the gain set by the scene's depth, so the front end's
median frame-to-frame flow is fitted to the wheels' distance over the same frame interval read at ``t + dt``,
with a gain per ``FLOW_BLOCK_S`` of frames that may drift linearly within it (a constant gain takes the depth's
change during a speed ramp for a time shift: +2.4 ms on a drift of 20% in 10 s). Only speed changes show the
offset (at a constant speed every ``dt`` fits), so this part counts only in blocks where the wheels' speed varies
by ``MIN_SPEED_VARIATION`` of its largest value (a stop or a start). Where both parts count and their own
estimates agree (a chi-square test at 99%), their residuals are added in units of each part's residual variance
(one chi-square curve over ``dt``); where they disagree there is no estimate.

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
# The speed part: frame intervals remembered, how many an estimate needs, the span (s) of frames that share one
# gain and its drift (the scene's depth changes slowly) and how much the wheels' per-frame distance must vary in
# such a span (share of its largest).
FLOW_WINDOW_FRAMES = 4000
MIN_FLOW_FRAMES = 20
FLOW_BLOCK_S = 2.0
MIN_SPEED_VARIATION = 0.5
# The speed part's residual variance understates its estimate's scatter: over 40 seeds of simulated stop-and-go
# drives (tests/test_wheel_clock_speed.py) the estimates scatter 1.6x (16 s) to 2.1x (30 s) more than the curvature
# says (the wheels' distance noise sits in the regressor, and the gains are fitted per block). Its curve is counted
# with the variance this many times squared larger (a wider sigma, a stricter test against zero).
FLOW_SIGMA_WIDENING = 2.0


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
    from_speed: bool = False  # the speed changes (image flow against wheel distance) counted in the estimate


@dataclass(frozen=True)
class _Interval:
    t0: float
    t1: float
    vision_yaw_rad: float  # heading change of the base from t0 to t1, from vision alone


@dataclass(frozen=True)
class _Flow:
    t0: float
    t1: float
    flow_px: float  # the front end's median image motion of its tracks from t0 to t1


class WheelClock:
    """Collects keyframe intervals with vision's heading change and estimates the wheels' time offset."""

    def __init__(self, max_offset_s: float = MAX_OFFSET_S, window: int = WINDOW_INTERVALS):
        self.max_offset_s = max_offset_s
        self.intervals: deque[_Interval] = deque(maxlen=window)
        self.flows: deque[_Flow] = deque(maxlen=FLOW_WINDOW_FRAMES)
        self.estimate = ClockEstimate()
        self.n_added = 0  # intervals added so far (the window may have dropped the oldest)
        self.n_flows_added = 0  # frame intervals with the image's motion added so far

    def add(self, t0: float, t1: float, vision_yaw_rad: float) -> None:
        """One keyframe interval and the base's heading change over it as vision measured it."""
        if t1 > t0 and np.isfinite(vision_yaw_rad):
            self.intervals.append(_Interval(float(t0), float(t1), float(vision_yaw_rad)))
            self.n_added += 1

    def add_flow(self, t0: float, t1: float, flow_px: float) -> None:
        """The front end's median image motion between two consecutive frames (``FrontendOutput.flow_px``)."""
        if t1 > t0 and np.isfinite(flow_px):
            self.flows.append(_Flow(float(t0), float(t1), float(flow_px)))
            self.n_flows_added += 1

    def update(self, wheels: WheelOdometry) -> ClockEstimate:
        """Re-estimate from the intervals so far; keeps the last observable estimate when this one is not."""
        est = estimate_offset(list(self.intervals), wheels, self.max_offset_s, list(self.flows))
        if est.observable:
            self.estimate = est
        else:
            self.estimate = ClockEstimate(self.estimate.offset_s, self.estimate.sigma_s, self.estimate.observable,
                                          est.n_intervals, self.estimate.zero_rejected,
                                          from_speed=self.estimate.from_speed)
        return self.estimate


def _distance(wheels: WheelOdometry) -> np.ndarray:
    """The wheels' distance driven up to each sample (m)."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(wheels.x), np.diff(wheels.y)))])


def _residuals(t0: np.ndarray, t1: np.ndarray, vis: np.ndarray, wheels: WheelOdometry,
               offsets: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Residual sum of squares of the linear fit wheel heading change ~ a * vision + b * distance (``s``: the
    wheels' distance at each sample), per offset."""
    ts, yaw = wheels.timestamps, wheels.yaw
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


def _speed_chi2(flows: list[_Flow], wheels: WheelOdometry, offsets: np.ndarray, max_offset_s: float,
                s: np.ndarray) -> np.ndarray | None:
    """The speed part's residual per offset, in residual variances (a chi-square curve); None where it does not
    count: too few frames, or no block of ``FLOW_BLOCK_S`` of frames in which the wheels' per-frame distance
    varies by ``MIN_SPEED_VARIATION`` of its largest (only speed changes show the offset; at a constant speed the
    curve would only follow the wheels' noise)."""
    if len(flows) < MIN_FLOW_FRAMES:
        return None
    t0 = np.array([f.t0 for f in flows])
    t1 = np.array([f.t1 for f in flows])
    y = np.array([f.flow_px for f in flows])
    ts = wheels.timestamps
    inside = (t0 - max_offset_s >= ts[0]) & (t1 + max_offset_s <= ts[-1])
    t0, t1, y = t0[inside], t1[inside], y[inside]
    if len(y) < 3:
        return None
    per_block = max(int(round(FLOW_BLOCK_S / float(np.median(t1 - t0)))), 3)
    n_blocks = len(y) // per_block
    if n_blocks == 0:
        return None
    m = n_blocks * per_block  # the newest whole blocks
    t0, t1 = t0[-m:].reshape(n_blocks, -1), t1[-m:].reshape(n_blocks, -1)
    y = y[-m:].reshape(n_blocks, -1)
    ds0 = np.interp(t1, ts, s) - np.interp(t0, ts, s)
    varies = np.ptp(ds0, axis=1) >= MIN_SPEED_VARIATION * np.max(np.abs(ds0), axis=1)
    varies &= np.max(np.abs(ds0), axis=1) > 0
    if not varies.any():
        return None
    t0, t1, y = t0[varies], t1[varies], y[varies]
    tau = t1 - np.mean(t1, axis=1, keepdims=True)  # the gain drifts linearly within a block (the depth changes)
    rss = np.empty(len(offsets))
    for i, dt in enumerate(offsets):
        ds = np.interp(t1 + dt, ts, s) - np.interp(t0 + dt, ts, s)
        a, b = ds, ds * tau
        # Per block, y ~ g0 * ds + g1 * tau * ds by least squares (2x2 normal equations).
        aa, ab, bb = np.sum(a * a, axis=1), np.sum(a * b, axis=1), np.sum(b * b, axis=1)
        ay, by = np.sum(a * y, axis=1), np.sum(b * y, axis=1)
        det = aa * bb - ab * ab
        # A block whose shifted readings move on one or two frames only (the rest standing) cannot tell the drift
        # from the gain: it gets one gain.
        two = det > 1e-9 * aa * bb
        safe = np.where(two, det, 1.0)
        g0 = np.where(two, (bb * ay - ab * by) / safe, ay / np.maximum(aa, 1e-300))
        g1 = np.where(two, (aa * by - ab * ay) / safe, 0.0)
        rss[i] = float(np.sum((y - g0[:, None] * a - g1[:, None] * b) ** 2))
    if not np.all(np.isfinite(rss)):
        return None
    sigma2 = float(np.min(rss)) / max(y.size - 2 * len(y), 1) * FLOW_SIGMA_WIDENING**2
    return rss / max(sigma2, 1e-300)


def _heading_rss(intervals: list[_Interval], wheels: WheelOdometry, offsets: np.ndarray, max_offset_s: float,
                 s: np.ndarray) -> tuple[np.ndarray | None, float, float, int]:
    """The heading part: its residual sum of squares per offset (None where it does not count: too few intervals,
    too little change of turn rate, or one only in proportion to the distance), its residual variance, the
    intervals' overlap and how many it used."""
    n = len(intervals)
    if n < MIN_INTERVALS:
        return None, 1.0, 1.0, n
    t0 = np.array([iv.t0 for iv in intervals])
    t1 = np.array([iv.t1 for iv in intervals])
    vis = np.array([iv.vision_yaw_rad for iv in intervals])
    # Keep the intervals whose shifted times the wheels cover at every offset of the grid.
    inside = (t0 - max_offset_s >= wheels.timestamps[0]) & (t1 + max_offset_s <= wheels.timestamps[-1])
    t0, t1, vis = t0[inside], t1[inside], vis[inside]
    rate = vis / (t1 - t0)
    if len(vis) < MIN_INTERVALS or float(np.ptp(rate * np.median(t1 - t0))) < MIN_TURN_VARIATION_RAD:
        return None, 1.0, 1.0, len(vis)
    # A turn rate that changes only with the speed (a circle driven stop-and-go) is the distance term again: the
    # heading must also change otherwise than in proportion to the distance driven.
    dist = np.interp(t1, wheels.timestamps, s) - np.interp(t0, wheels.timestamps, s)
    beyond = vis - dist * float(dist @ vis) / max(float(dist @ dist), 1e-300)
    if float(np.ptp(beyond)) < MIN_TURN_VARIATION_RAD:
        return None, 1.0, 1.0, len(vis)
    rss = _residuals(t0, t1, vis, wheels, offsets, s)
    sigma2 = float(rss[int(np.argmin(rss))]) / max(len(vis) - 3, 1)
    return rss, sigma2, _overlap(t0, t1), len(vis)


def _minimum(rss: np.ndarray, offsets: np.ndarray, sigma2: float, overlap: float, n: int,
             from_speed: bool) -> ClockEstimate:
    """The offset at a residual curve's minimum, refined by a parabola through its neighbours, its standard error
    from the curvature (``sigma2``: the residual variance, ``overlap``: how many residuals share each instant's
    noise) and the likelihood-ratio test against a zero offset."""
    if not np.all(np.isfinite(rss)):
        return ClockEstimate(n_intervals=n)
    i = int(np.argmin(rss))
    if i == 0 or i == len(offsets) - 1:  # at the edge of the search: no minimum inside it
        return ClockEstimate(n_intervals=n)
    r_m, r_0, r_p = rss[i - 1], rss[i], rss[i + 1]
    curvature = (r_p - 2.0 * r_0 + r_m) / GRID_STEP_S**2
    if not curvature > 0:
        return ClockEstimate(n_intervals=n)
    shift = 0.5 * (r_m - r_p) / (r_p - 2.0 * r_0 + r_m) * GRID_STEP_S
    offset = float(offsets[i] + np.clip(shift, -GRID_STEP_S, GRID_STEP_S))
    # Gauss-Newton: var(dt) = 2 sigma^2 / RSS''(dt), with sigma^2 the residual variance of the fit; times the
    # intervals' overlap (each instant covered by that many of them on average), as they are not independent.
    sigma_s = float(np.sqrt(2.0 * sigma2 / curvature * overlap))
    rss_zero = float(rss[int(np.argmin(np.abs(offsets)))])
    zero_rejected = bool((rss_zero - r_0) / max(sigma2 * overlap, 1e-300) > CHI2_1DOF_99)
    return ClockEstimate(offset, sigma_s, sigma_s <= MAX_SIGMA_S, n, zero_rejected, from_speed=from_speed)


def estimate_offset(intervals: list[_Interval], wheels: WheelOdometry, max_offset_s: float = MAX_OFFSET_S,
                    flows: list[_Flow] | None = None) -> ClockEstimate:
    """The offset that best explains the wheels' heading changes by vision's, and their distance per frame by the
    image's motion where the speed changes (see the module docstring)."""
    offsets = np.arange(-max_offset_s, max_offset_s + GRID_STEP_S / 2, GRID_STEP_S)
    s = _distance(wheels)
    rss_h, sigma2, overlap, n = _heading_rss(intervals, wheels, offsets, max_offset_s, s)
    chi_v = _speed_chi2(flows, wheels, offsets, max_offset_s, s) if flows else None
    if chi_v is None:
        return _minimum(rss_h, offsets, sigma2, overlap, n, False) if rss_h is not None else ClockEstimate(n_intervals=n)
    if rss_h is None:
        return _minimum(chi_v, offsets, 1.0, 1.0, n, True)
    chi_h = rss_h / max(sigma2 * overlap, 1e-300)
    if not _consistent(_minimum(chi_h, offsets, 1.0, 1.0, n, False), _minimum(chi_v, offsets, 1.0, 1.0, n, True)):
        return ClockEstimate(n_intervals=n)
    return _minimum(chi_h + chi_v, offsets, 1.0, 1.0, n, True)


def _consistent(turns: ClockEstimate, speed: ClockEstimate) -> bool:
    """Whether the turns' and the speed's own estimates tell the same offset (a chi-square test of their difference
    at 99%, each with its sigma); one part without a minimum of its own does not contradict the other. Two parts
    that disagree are not added: one of them is biased (the turns of a stop-and-go warehouse loop put the offset 30 ms
    off with a sigma of 3.6 ms), and their sum would look better known than either."""
    if not (np.isfinite(turns.sigma_s) and np.isfinite(speed.sigma_s)):
        return True
    diff2 = (turns.offset_s - speed.offset_s) ** 2
    return bool(diff2 <= CHI2_1DOF_99 * (turns.sigma_s**2 + speed.sigma_s**2))
