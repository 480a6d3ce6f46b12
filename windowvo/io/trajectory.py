"""Trajectories as timestamped ``T_world_base`` poses, and the text formats they are read from.

* TUM: one pose a line, ``t tx ty tz qx qy qz qw`` (seconds, metres, unit quaternion); ``#``
  comment lines (windowvo writes a header) are skipped.
* KITTI odometry ``poses.txt``: one pose a line, 12 numbers, the row-major 3x4 ``T_cam0_camk``
  (camera 0 at frame k in camera 0 at frame 0; camera axes x right, y down, z forward). No times:
  they come from a ``times.txt`` beside the file, else frame index times a period.

Text is decoded as UTF-8 with undecodable bytes replaced (a cp1252 byte in a comment must not
stop a run).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SequenceError
from ..geometry import R_BASE_CAM_FORWARD, R_from_quat, inv_T, make_T, quat_from_R

# Height of KITTI's camera 0 above the road (KITTI set-up); the same number as
# the KITTI loader (``windowvo.io.kitti``).
KITTI_CAMERA_HEIGHT_M = 1.65
KITTI_DEFAULT_DT_S = 0.1  # KITTI odometry is recorded at about 10 Hz
TUM_COLUMNS = 8
KITTI_COLUMNS = 12


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


def read_text_lenient(path: Path) -> str:
    """A text file's content: UTF-8 with undecodable bytes (e.g. cp1252 in a comment) replaced.

    Raises :class:`SequenceError` when the file is missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise SequenceError(f"trajectory file not found: {path}")
    try:
        return path.read_bytes().decode("utf-8", errors="replace")
    except OSError as err:
        raise SequenceError(f"cannot read {path}: {err.strerror or err}") from None


def _numeric_rows(path: Path, n_cols: int, what: str) -> np.ndarray:
    """The non-comment lines of a whitespace (or comma) separated table, each exactly ``n_cols`` numbers."""
    rows = []
    for lineno, line in enumerate(read_text_lenient(path).splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != n_cols:
            raise SequenceError(f"{path.name}:{lineno}: expected {n_cols} numbers {what}, got {len(parts)}")
        try:
            rows.append([float(x) for x in parts])
        except ValueError:
            raise SequenceError(f"{path.name}:{lineno}: not a number in '{s}'") from None
    if not rows:
        raise SequenceError(f"{path.name}: no poses")
    a = np.asarray(rows)
    if not np.all(np.isfinite(a)):
        raise SequenceError(f"{path.name}: non-finite values")
    return a


def _check_increasing(name: str, t: np.ndarray) -> None:
    if np.any(np.diff(t) <= 0):
        raise SequenceError(f"{name}: timestamps are not strictly increasing")


def read_tum(path: Path) -> Trajectory:
    path = Path(path)
    a = _numeric_rows(path, TUM_COLUMNS, "'t tx ty tz qx qy qz qw'")
    _check_increasing(path.name, a[:, 0])
    poses = np.stack([make_T(R_from_quat(r[4:8]), r[1:4]) for r in a])
    return Trajectory(a[:, 0], poses)


# ---------------------------------------------------------------------------- KITTI poses


def kitti_T_base_cam0(camera_height_m: float = KITTI_CAMERA_HEIGHT_M) -> np.ndarray:
    """windowvo's KITTI base: on the road ``camera_height_m`` below camera 0, robot axes
    (x forward, y left, z up). The convention of the KITTI loader (``io.kitti.load_kitti``)."""
    return make_T(R_BASE_CAM_FORWARD, np.array([0.0, 0.0, camera_height_m]))


def kitti_cam0_to_base(T_cam0_camk: np.ndarray, camera_height_m: float = KITTI_CAMERA_HEIGHT_M) -> np.ndarray:
    """KITTI ground truth (N, 4, 4) ``T_cam0_camk`` as windowvo's ``T_world_base``:
    ``T_base_cam T_cam0_camk T_cam_base`` (world = the base at frame 0). The KITTI loader then
    re-anchors on its first pose, which changes nothing when frame 0 is the identity."""
    T_bc = kitti_T_base_cam0(camera_height_m)
    return np.einsum("ij,njk,kl->nil", T_bc, np.asarray(T_cam0_camk, float), inv_T(T_bc))


def read_kitti_cam0_poses(path: Path) -> np.ndarray:
    """The (N, 4, 4) ``T_cam0_camk`` of a KITTI ``poses.txt`` (12 numbers a line).

    The file's rotations are printed to 7 digits, so they are orthonormal only to ~1e-7: each is
    replaced by the nearest rotation (SVD), else a rotation error's ``acos`` near 1 turns that
    rounding into ~3e-4 rad per segment. Rows farther than 1e-3 from a rotation are an error."""
    path = Path(path)
    a = _numeric_rows(path, KITTI_COLUMNS, "(a row-major 3x4 KITTI pose)")
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :] = a.reshape(-1, 3, 4)
    U, sv, Vt = np.linalg.svd(T[:, :3, :3])
    bad = np.flatnonzero((np.abs(sv - 1.0).max(axis=1) > 1e-3) | (np.linalg.det(T[:, :3, :3]) <= 0))
    if len(bad):
        raise SequenceError(f"{path.name}:{bad[0] + 1}: the 3x3 part is not a rotation (KITTI poses expected)")
    T[:, :3, :3] = U @ Vt
    return T


def read_times_column(path: Path, n: int) -> np.ndarray:
    """First column of a KITTI ``times.txt``: ``n`` strictly increasing seconds."""
    path = Path(path)
    vals = []
    for lineno, line in enumerate(read_text_lenient(path).splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            vals.append(float(s.replace(",", " ").split()[0]))
        except ValueError:
            raise SequenceError(f"{path.name}:{lineno}: not a timestamp: '{s}'") from None
    t = np.asarray(vals, dtype=float)
    if len(t) != n:
        raise SequenceError(f"{path} has {len(t)} timestamps but the poses file has {n} poses")
    if not np.all(np.isfinite(t)):
        raise SequenceError(f"{path.name}: non-finite timestamps")
    _check_increasing(path.name, t)
    return t


# ---------------------------------------------------------------------------- any format


class TrajectoryFormat(enum.Enum):
    TUM = "tum"  # t tx ty tz qx qy qz qw (windowvo's own outputs: TUM with a '#' header)
    KITTI = "kitti"  # 3x4 T_cam0_camk, row major


class TimesSource(enum.Enum):
    IN_FILE = "in the file"  # TUM's first column
    TIMES_TXT = "times.txt"  # beside a KITTI poses file
    FRAME_INDEX = "frame index"  # frame index times a period


@dataclass(frozen=True)
class LoadedTrajectory:
    """A trajectory file as read: the poses (``T_world_base``) and how they were read."""

    trajectory: Trajectory
    format: TrajectoryFormat
    times: TimesSource
    dt_s: float | None = None  # the period, when the times are frame index * dt_s
    detected: bool = True  # False when the format was forced

    def describe(self) -> str:
        """E.g. ``KITTI poses (12 numbers/line), 51 poses, times from times.txt``."""
        n = len(self.trajectory)
        if self.format is TrajectoryFormat.TUM:
            head = f"TUM (8 numbers/line), {n} poses"
        else:
            head = f"KITTI poses (12 numbers/line, camera 0 -> windowvo base), {n} poses"
            if self.times is TimesSource.TIMES_TXT:
                head += ", times from times.txt"
            else:
                head += f", times = frame index x {self.dt_s:g} s (no times.txt beside it)"
        return head + ("" if self.detected else " (format forced)")


def detect_format(path: Path) -> TrajectoryFormat:
    """TUM or KITTI from the number of columns of the first pose line (8 or 12)."""
    path = Path(path)
    for lineno, line in enumerate(read_text_lenient(path).splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        n = len(s.replace(",", " ").split())
        if n == TUM_COLUMNS:
            return TrajectoryFormat.TUM
        if n == KITTI_COLUMNS:
            return TrajectoryFormat.KITTI
        raise SequenceError(f"{path.name}:{lineno}: expected 8 numbers (TUM: t tx ty tz qx qy qz qw) or 12 "
                            f"(KITTI poses: a row-major 3x4 pose), got {n}")
    raise SequenceError(f"{path.name}: no poses")


def read_trajectory(path: Path, fmt: TrajectoryFormat | None = None, *,
                    kitti_dt_s: float = KITTI_DEFAULT_DT_S) -> LoadedTrajectory:
    """Read a TUM or KITTI poses file (``fmt=None``: detected from the column count).

    KITTI poses become windowvo ``T_world_base`` by :func:`kitti_cam0_to_base`; their times come from
    ``times.txt`` in the same folder when it exists, else frame index * ``kitti_dt_s``."""
    path = Path(path)
    detected = fmt is None
    fmt = detect_format(path) if fmt is None else fmt
    if fmt is TrajectoryFormat.TUM:
        return LoadedTrajectory(read_tum(path), fmt, TimesSource.IN_FILE, detected=detected)
    if not (kitti_dt_s > 0 and np.isfinite(kitti_dt_s)):
        raise SequenceError(f"the KITTI frame period must be positive, got {kitti_dt_s}")
    T_cam0_camk = read_kitti_cam0_poses(path)
    times_txt = path.parent / "times.txt"
    if times_txt.is_file():
        t = read_times_column(times_txt, len(T_cam0_camk))
        source, dt = TimesSource.TIMES_TXT, None
    else:
        t = kitti_dt_s * np.arange(len(T_cam0_camk), dtype=float)
        source, dt = TimesSource.FRAME_INDEX, kitti_dt_s
    return LoadedTrajectory(Trajectory(t, kitti_cam0_to_base(T_cam0_camk)), fmt, source, dt, detected)


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
        self._fh.flush()  # the header is on disk from the start: a killed run's journal is never a 0-byte file
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
