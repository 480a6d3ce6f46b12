"""Wheel odometry: integrated planar poses of the base in the odometry frame.

File ``odometry.csv`` with header ``timestamp,x,y,yaw``. Lines starting with ``#`` are comments
(synthesised odometry says so there).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SequenceError
from ..geometry import inv_T, planar_T

log = logging.getLogger(__name__)

# Faster than any ground vehicle: a wheel sample that moves the base faster than this since the previous one (plus
# TELEPORT_SLACK_M for timestamp jitter) is a teleport (an odometry reset, a corrupt message), not motion. Proposed
# The default of the config key backend.odometry.max_speed_m_s.
MAX_WHEEL_SPEED_M_S = 60.0
TELEPORT_SLACK_M = 0.5


def _lerp(t: float, t0: float, t1: float, y0: float, y1: float) -> float:
    """``np.interp``'s value at t strictly between samples (t0, y0) and (t1, y1), computed as it computes it. One
    binary search for x, y and yaw instead of three ``np.interp`` calls (17 -> 5 us a pose, 13 poses a frame)."""
    slope = (y1 - y0) / (t1 - t0)
    v = slope * (t - t0) + y0
    if v != v:  # nan: np.interp's fallback from the right end
        v = slope * (t - t1) + y1
        if v != v and y0 == y1:
            v = y0
    return v


@dataclass
class WheelOdometry:
    timestamps: np.ndarray  # (N,)
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray  # unwrapped
    comment: str = ""
    # A streamed odometry may be asked for a time just past its newest sample (the frame came first):
    # poses up to this many seconds past the end are extrapolated at the last velocity.
    extrapolate_s: float = 0.0
    # Times of samples rejected as teleports (WheelBuffer): a step across one has no usable wheel data.
    rejected_times: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def synthetic(self) -> bool:
        return "synthetic" in self.comment.lower()

    def on_camera_clock(self, offset_s: float) -> WheelOdometry:
        """The same samples stamped on the camera's clock, for wheels whose clock is ``offset_s`` ahead of it
        (``t_wheels = t_camera + offset_s``): a reading at camera time t is the wheels' pose at t + offset_s."""
        if offset_s == 0.0:
            return self
        return WheelOdometry(self.timestamps - offset_s, self.x, self.y, self.yaw, self.comment, self.extrapolate_s,
                             self.rejected_times - offset_s)

    def covers(self, t: float, tol: float = 1e-6) -> bool:
        return self.timestamps[0] - tol <= t <= self.timestamps[-1] + tol + self.extrapolate_s

    def pose_at(self, t: float) -> np.ndarray:
        """T_odom_base at time t, linearly interpolated (clamped at the start; past the end, extrapolated
        for up to ``extrapolate_s``, then clamped)."""
        ts = self.timestamps
        last = float(ts[-1])
        if t > last and self.extrapolate_s > 0 and len(ts) >= 2:
            dt = float(ts[-1] - ts[-2])
            s = min(t - last, self.extrapolate_s) / max(dt, 1e-9)
            return planar_T(float(self.x[-1] + s * (self.x[-1] - self.x[-2])),
                            float(self.y[-1] + s * (self.y[-1] - self.y[-2])),
                            float(self.yaw[-1] + s * (self.yaw[-1] - self.yaw[-2])))
        if len(ts) == 1:
            j = 0
        elif not t < last:  # np.interp's right end (and a nan time)
            j = len(ts) - 1 if t >= last else -1
        elif t < float(ts[0]):
            j = 0
        else:
            j = int(np.searchsorted(ts, t, side="right")) - 1
            t0 = float(ts[j])
            if t != t0:  # strictly inside [t0, t1): np.interp's own formula, so the same doubles
                t1 = float(ts[j + 1])
                return planar_T(*(_lerp(t, t0, t1, float(v[j]), float(v[j + 1])) for v in (self.x, self.y, self.yaw)))
        if j < 0:
            return planar_T(float("nan"), float("nan"), float("nan"))
        return planar_T(float(self.x[j]), float(self.y[j]), float(self.yaw[j]))

    def delta(self, t0: float, t1: float) -> np.ndarray:
        """T_base0_base1: base motion from t0 to t1 according to the wheels."""
        return inv_T(self.pose_at(t0)) @ self.pose_at(t1)

    def distance(self, t0: float, t1: float) -> float:
        """Path length driven between t0 and t1 (sums the samples in between)."""
        ts = self.timestamps
        # The samples strictly between t0 and t1, by binary search (a mask over every sample cost a long run's
        # frames more as the wheel log grew: 0.2 ms a call at an hour of 100 Hz samples).
        i0, i1 = int(np.searchsorted(ts, t0, side="right")), int(np.searchsorted(ts, t1, side="left"))
        inside = slice(i0, max(i0, i1))
        p0, p1 = self.pose_at(t0), self.pose_at(t1)
        px = np.concatenate([[p0[0, 3]], self.x[inside], [p1[0, 3]]])
        py = np.concatenate([[p0[1, 3]], self.y[inside], [p1[1, 3]]])
        return float(np.hypot(np.diff(px), np.diff(py)).sum())

    def max_gap_in(self, t0: float, t1: float) -> float:
        """Largest time between consecutive samples that bracket [t0, t1]; infinite when a sample between them was
        rejected as a teleport (the step then has no trustworthy wheel data)."""
        ts = self.timestamps
        if len(self.rejected_times) and np.any((self.rejected_times > t0) & (self.rejected_times <= t1)):
            return float("inf")
        i0 = max(int(np.searchsorted(ts, t0, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(ts, t1, side="left")), len(ts) - 1)
        if i1 <= i0:
            return 0.0
        return float(np.max(np.diff(ts[i0 : i1 + 1])))


class WheelBuffer:
    """Wheel odometry that grows sample by sample (a robot's stream); ``view()`` is a :class:`WheelOdometry`
    of the samples so far (no copy: arrays grow by doubling), extrapolated a little past the newest one."""

    def __init__(self, extrapolate_s: float, comment: str = ""):
        self.extrapolate_s = extrapolate_s
        self.comment = comment
        self._a = np.zeros((4, 1024))  # rows: t, x, y, yaw (unwrapped)
        self._n = 0
        self._view: WheelOdometry | None = None
        self.max_speed_m_s = MAX_WHEEL_SPEED_M_S
        self._raw_last: tuple[float, float, float] | None = None  # the previous sample as it came (x, y, yaw)
        self._T_fix: np.ndarray | None = None  # corrects the samples after a rejected teleport: T_odom_odomraw
        self.rejected: list[float] = []  # times of the samples rejected as teleports

    def __len__(self) -> int:
        return self._n

    @property
    def last_time(self) -> float:
        return float(self._a[0, self._n - 1]) if self._n else -np.inf

    def append(self, t: float, x: float, y: float, yaw: float) -> None:
        if not all(np.isfinite(v) for v in (t, x, y, yaw)):
            raise SequenceError(f"wheel odometry sample at t={t} is not finite")
        if self._n and t <= self.last_time:
            raise SequenceError(f"wheel odometry timestamps must increase: {t} after {self.last_time}")
        x, y, yaw = self._untangle(t, x, y, yaw)
        if self._n:  # unwrap the yaw against the previous sample
            prev = float(self._a[3, self._n - 1])
            yaw = prev + float(np.angle(np.exp(1j * (yaw - prev))))
        if self._n == self._a.shape[1]:
            self._a = np.concatenate([self._a, np.zeros_like(self._a)], axis=1)
        self._a[:, self._n] = (t, x, y, yaw)
        self._n += 1
        self._view = None

    def _untangle(self, t: float, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """The sample in the buffer's odometry frame. A jump no vehicle can drive since the previous sample is
        rejected (warning; the base is held where it was, and the samples after it continue from there)."""
        raw = (x, y, yaw)
        last, self._raw_last = self._raw_last, raw
        if last is not None and self._n:
            dt = t - self.last_time
            jump = float(np.hypot(x - last[0], y - last[1]))
            if jump > self.max_speed_m_s * dt + TELEPORT_SLACK_M:
                prev = self._a[1:, self._n - 1]
                self._T_fix = planar_T(float(prev[0]), float(prev[1]), float(prev[2])) @ inv_T(planar_T(x, y, yaw))
                self.rejected.append(float(t))
                log.warning("wheel odometry jumps %.1f m in %.3f s at t=%.3f s (%.0f m/s, faster than any vehicle: "
                            "above %.0f m/s): sample rejected, vision only for that step", jump, dt, t,
                            jump / max(dt, 1e-9), self.max_speed_m_s)
        if self._T_fix is None:
            return x, y, yaw
        T = self._T_fix @ planar_T(x, y, yaw)
        return float(T[0, 3]), float(T[1, 3]), float(np.arctan2(T[1, 0], T[0, 0]))

    def view(self) -> WheelOdometry | None:
        if self._n < 2:
            return None
        if self._view is None:
            a = self._a[:, : self._n]
            self._view = WheelOdometry(a[0], a[1], a[2], a[3], self.comment, self.extrapolate_s,
                                       np.asarray(self.rejected, float))
        return self._view


def read_odometry_csv(path: Path) -> WheelOdometry:
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise SequenceError(f"cannot read {path.name}: {err}") from None
    comments = []
    rows = []
    header_seen = False
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s.lstrip("# "))
            continue
        if not header_seen:
            cols = [c.strip().lower() for c in s.split(",")]
            if cols != ["timestamp", "x", "y", "yaw"]:
                raise SequenceError(f"{path.name}: header must be 'timestamp,x,y,yaw', got '{s}'")
            header_seen = True
            continue
        parts = s.split(",")
        if len(parts) != 4:
            raise SequenceError(f"{path.name}:{lineno}: expected 4 comma-separated values, got {len(parts)}")
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise SequenceError(f"{path.name}:{lineno}: not a number in '{s}'") from None
        rows.append(vals)
    if not header_seen:
        raise SequenceError(f"{path.name}: missing header 'timestamp,x,y,yaw'")
    if len(rows) < 2:
        raise SequenceError(f"{path.name}: needs at least 2 samples, got {len(rows)}")
    a = np.asarray(rows, dtype=float)
    if not np.all(np.isfinite(a)):
        raise SequenceError(f"{path.name}: contains non-finite values (nan or inf)")
    if np.any(np.diff(a[:, 0]) <= 0):
        raise SequenceError(f"{path.name}: timestamps must be strictly increasing")
    return WheelOdometry(a[:, 0], a[:, 1], a[:, 2], np.unwrap(a[:, 3]), comment="\n".join(comments))


def write_odometry_csv(path: Path, odo: WheelOdometry) -> None:
    lines = [f"# {c}" for c in odo.comment.splitlines() if c]
    lines.append("timestamp,x,y,yaw")
    for t, x, y, yaw in zip(odo.timestamps, odo.x, odo.y, odo.yaw):
        lines.append(f"{t:.6f},{x:.6f},{y:.6f},{yaw:.8f}")
    Path(path).write_text("\n".join(lines) + "\n")
