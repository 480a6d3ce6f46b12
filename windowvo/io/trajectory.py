"""Trajectories as timestamped ``T_world_base`` poses, and the TUM text format.

TUM format: one pose a line, ``t tx ty tz qx qy qz qw`` (seconds, metres, unit quaternion).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SequenceError
from ..geometry import R_from_quat, inv_T, make_T, quat_from_R


@dataclass
class Trajectory:
    timestamps: np.ndarray  # (N,)
    T_world_base: np.ndarray  # (N, 4, 4)

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.T_world_base[:, :3, 3]

    def path_length(self) -> float:
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())

    def anchored(self) -> Trajectory:
        """Re-express in the frame of the first pose (world = base at the first frame)."""
        T0_inv = inv_T(self.T_world_base[0])
        return Trajectory(self.timestamps.copy(), np.einsum("ij,njk->nik", T0_inv, self.T_world_base))


def tum_line(t: float, T: np.ndarray) -> str:
    """One TUM line (t tx ty tz qx qy qz qw) of a 4x4 pose."""
    q = quat_from_R(T[:3, :3])
    p = T[:3, 3]
    return f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"


def write_tum(path: Path, timestamps: np.ndarray, poses: np.ndarray, header: str | None = None) -> None:
    """Write poses atomically (temp file then rename) so a crash never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines: list[str] = []
    if header:
        lines.extend(f"# {h}" for h in header.splitlines())
    lines.extend(tum_line(float(t), T) for t, T in zip(timestamps, poses))
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text("\n".join(lines) + ("\n" if lines else ""))
    tmp.replace(path)


def read_tum(path: Path) -> Trajectory:
    path = Path(path)
    if not path.is_file():
        raise SequenceError(f"trajectory file not found: {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise SequenceError(f"{path.name}:{lineno}: expected 8 numbers 't tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            rows.append([float(x) for x in parts])
        except ValueError:
            raise SequenceError(f"{path.name}:{lineno}: not a number in '{s}'") from None
    if not rows:
        raise SequenceError(f"{path.name}: no poses")
    a = np.asarray(rows)
    if not np.all(np.isfinite(a)):
        raise SequenceError(f"{path.name}: non-finite values")
    if np.any(np.diff(a[:, 0]) <= 0):
        raise SequenceError(f"{path.name}: timestamps are not strictly increasing")
    poses = np.stack([make_T(R_from_quat(r[4:8]), r[1:4]) for r in a])
    return Trajectory(a[:, 0], poses)


class TumJournal:
    """A TUM file written as a run goes: lines are appended and flushed in batches, so a process killed
    at any moment (SIGKILL, out of memory) leaves every flushed line readable. Only for poses that never
    change once written (the causal trajectory); the final file is rewritten atomically at the end."""

    def __init__(self, path: Path, header: str):
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._fh = path.open("w")
        self._fh.write("".join(f"# {h}\n" for h in header.splitlines()))
        self._pending: list[str] = []

    def add(self, t: float, T: np.ndarray) -> None:
        self._pending.append(tum_line(t, T))

    def flush(self) -> None:
        if self._pending and not self._fh.closed:
            self._fh.write("\n".join(self._pending) + "\n")
            self._fh.flush()
            self._pending = []

    def close(self) -> None:
        self.flush()
        self._fh.close()
