"""Wheel odometry: integrated planar poses of the base in the odometry frame.

File ``odometry.csv`` with header ``timestamp,x,y,yaw``. Lines starting with ``#`` are comments
(synthesised odometry says so there).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SequenceError
from ..geometry import inv_T, planar_T


@dataclass
class WheelOdometry:
    timestamps: np.ndarray  # (N,)
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray  # unwrapped
    comment: str = ""

    @property
    def synthetic(self) -> bool:
        return "synthetic" in self.comment.lower()

    def covers(self, t: float, tol: float = 1e-6) -> bool:
        return self.timestamps[0] - tol <= t <= self.timestamps[-1] + tol

    def pose_at(self, t: float) -> np.ndarray:
        """T_odom_base at time t, linearly interpolated (clamped at the ends)."""
        ts = self.timestamps
        x = np.interp(t, ts, self.x)
        y = np.interp(t, ts, self.y)
        yaw = np.interp(t, ts, self.yaw)
        return planar_T(float(x), float(y), float(yaw))

    def delta(self, t0: float, t1: float) -> np.ndarray:
        """T_base0_base1: base motion from t0 to t1 according to the wheels."""
        return inv_T(self.pose_at(t0)) @ self.pose_at(t1)

    def distance(self, t0: float, t1: float) -> float:
        """Path length driven between t0 and t1 (sums the samples in between)."""
        ts = self.timestamps
        inside = (ts > t0) & (ts < t1)
        px = np.concatenate([[np.interp(t0, ts, self.x)], self.x[inside], [np.interp(t1, ts, self.x)]])
        py = np.concatenate([[np.interp(t0, ts, self.y)], self.y[inside], [np.interp(t1, ts, self.y)]])
        return float(np.hypot(np.diff(px), np.diff(py)).sum())

    def max_gap_in(self, t0: float, t1: float) -> float:
        """Largest time between consecutive samples that bracket [t0, t1]."""
        ts = self.timestamps
        i0 = max(int(np.searchsorted(ts, t0, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(ts, t1, side="left")), len(ts) - 1)
        if i1 <= i0:
            return 0.0
        return float(np.max(np.diff(ts[i0 : i1 + 1])))


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
