"""The run journal ``journal.jsonl``: what a hard kill (SIGKILL, out of memory, power loss) cannot take back.

One JSON object per line, append-only, header first; the lines are flushed to the OS at every keyframe, so a
process killed at any moment loses at most the frames since the last keyframe that was finished. Lines:

- ``{"journal": "windowvo", "version": 1, ...}``: the header (written and flushed when the run starts);
- ``{"frame": {stats.csv row}, "T_online": [16], "wheel_m": d}``: every frame, as it is finished (its stats row,
  its causal pose, the wheel distance driven since the previous keyframe: the smoothed trajectory places the
  frames between two keyframes by it);
- ``{"keyframe": i, "t": t, "T_world_base": [16]}``: a keyframe's smoothed pose once it is final (it left the
  fixed-lag window: marginalised, never changed again). A monocular run made metric late rescales every keyframe
  before the window: they are journaled again, and the last line of a keyframe is its pose;
- ``{"segment": {..., "first_frame": k}}``: a continuation (``--resume``) starts here; its frame and keyframe lines
  follow, with frame indices of the whole sequence and poses in the continuation's own world (its base at frame
  ``k``, its own scale);
- ``{"end": "complete" | "interrupted" | "resumed"}``: the run (or the continuation) ended and its outputs were
  written (``resumed``: by a ``--resume`` that had no frame left to run).

:func:`read_journal` reads a (possibly cut) journal back, the continuations placed into the first run's world
(:func:`seam`), and :func:`resumed_trajectory` rebuilds the smoothed trajectory from it.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import WindowVOError
from ..geometry import interpolate_T, inv_T
from ..io.trajectory import Trajectory
from ..types import FrameRecord

JOURNAL_NAME = "journal.jsonl"
JOURNAL_VERSION = 1
# A frame record's fields, in order: its journal line is a flat dict of them (``dataclasses.asdict`` copies
# recursively: 50 us a record against 4, for a record that holds no container).
_RECORD_FIELDS = tuple(f.name for f in dataclasses.fields(FrameRecord))


class JournalError(WindowVOError):
    """The journal is missing, not a windowvo journal, or holds no frame."""


class RunJournal:
    """Appends the journal's lines; :meth:`flush` (at every keyframe) hands them to the OS."""

    def __init__(self, path: Path, header: dict, first_frame: int | None = None):
        """A new journal; with ``first_frame``, a continuation segment appended to the existing one (a line cut
        by the kill is ended first, so the segment's header line stays readable)."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if first_frame is None:
            self._fh = self.path.open("w")
            self._pending: list[str] = [json.dumps({"journal": "windowvo", "version": JOURNAL_VERSION, **header})]
        else:
            cut = _ends_without_newline(self.path)
            self._fh = self.path.open("a")
            self._pending = [("\n" if cut else "") + json.dumps({"segment": {**header,
                                                                            "first_frame": int(first_frame)}})]
        self.flush()

    def frame(self, record: FrameRecord, T_online: np.ndarray, wheel_m: float | None) -> None:
        self._pending.append(json.dumps({"frame": {k: getattr(record, k) for k in _RECORD_FIELDS}, "T_online": _flat(T_online),
                                         "wheel_m": wheel_m}))

    def keyframe(self, index: int, t: float, T_world_base: np.ndarray) -> None:
        self._pending.append(json.dumps({"keyframe": int(index), "t": float(t), "T_world_base": _flat(T_world_base)}))

    def flush(self) -> None:
        if self._pending and not self._fh.closed:
            self._fh.write("\n".join(self._pending) + "\n")
            self._fh.flush()
            self._pending = []

    def close(self, end: str | None = None) -> None:
        if self._fh.closed:
            return
        if end is not None:
            self._pending.append(json.dumps({"end": end}))
        self.flush()
        self._fh.close()


def mark_end(path: Path, end: str) -> None:
    """Append an end line to a journal whose run could not (``--resume`` wrote its outputs)."""
    with Path(path).open("a") as fh:
        fh.write(json.dumps({"end": end}) + "\n")


def _ends_without_newline(path: Path) -> bool:
    with Path(path).open("rb") as fh:
        fh.seek(0, 2)
        if fh.tell() == 0:
            return False
        fh.seek(-1, 2)
        return fh.read(1) != b"\n"


def _flat(T: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(T, float).ravel()]


@dataclass
class JournalContents:
    """What a journal holds: the header, one entry per finished frame, the final keyframe poses.

    :func:`read_journal` gives the whole sequence's view: the segments of continuations (``--resume``) placed
    into the first run's world (``resumed_from``: the frame each one continued from)."""

    header: dict
    records: list[FrameRecord] = field(default_factory=list)
    online: list[np.ndarray] = field(default_factory=list)  # causal T_world_base per frame
    wheel_m: list[float | None] = field(default_factory=list)
    final_keyframes: dict[int, tuple[float, np.ndarray]] = field(default_factory=dict)  # index -> (t, T_world_base)
    end: str | None = None
    n_bad_lines: int = 0  # unreadable lines (the last one, cut by the kill)
    first_frame: int = 0  # a segment's first frame (its poses: world = base at that frame)
    resumed_from: list[int] = field(default_factory=list)

    @property
    def timestamps(self) -> np.ndarray:
        return np.asarray([r.timestamp for r in self.records], float)

    @property
    def metric_cue(self) -> bool:
        """The run had wheels or the floor for its scale (else its scale is arbitrary, one per run)."""
        return bool(self.header.get("use_odometry") or self.header.get("use_ground"))


def read_journal(path: Path) -> JournalContents:
    """Read a journal, skipping a line cut short by a kill; continuation segments are placed by :func:`seam`."""
    try:
        lines = Path(path).read_text(errors="replace").splitlines()
    except OSError as err:
        raise JournalError(f"no journal to resume from: {err.strerror}: {path}") from None
    header = _parse(lines[0]) if lines else None
    if not isinstance(header, dict) or header.get("journal") != "windowvo":
        raise JournalError(f"{path} is not a windowvo journal")
    pieces = [JournalContents(header)]
    names = {f.name for f in dataclasses.fields(FrameRecord)}
    for line in lines[1:]:
        obj = _parse(line)
        out = pieces[-1]
        if not isinstance(obj, dict):
            out.n_bad_lines += 1
        elif "frame" in obj:
            out.records.append(FrameRecord(**{k: v for k, v in obj["frame"].items() if k in names}))
            out.online.append(np.asarray(obj["T_online"], float).reshape(4, 4))
            out.wheel_m.append(obj.get("wheel_m"))
        elif "keyframe" in obj:
            out.final_keyframes[int(obj["keyframe"])] = (float(obj["t"]),
                                                         np.asarray(obj["T_world_base"], float).reshape(4, 4))
        elif "segment" in obj:
            seg = obj["segment"]
            pieces.append(JournalContents({**header, **seg}, first_frame=int(seg["first_frame"])))
        elif "end" in obj:
            out.end = str(obj["end"])
    whole = pieces[0]
    for piece in pieces[1:]:
        whole = continued(whole, piece)
    return whole


@dataclass(frozen=True)
class Seam:
    """Where a continuation joins the run it continues: frames up to ``first_frame`` (``n_prefix`` journal rows)
    are the earlier run's, later ones the continuation's, placed by :meth:`place`. The continuation may have
    started earlier (a warm-up): its pose of ``first_frame`` is then where it joins."""

    first_frame: int
    n_prefix: int
    T_world_start: np.ndarray  # the earlier run's pose of frame first_frame
    T_start_cworld: np.ndarray  # the inverse of the continuation's own pose of frame first_frame
    scale: float  # the earlier run's length unit per continuation unit (1 when both are metric)

    def place(self, T_cworld_base: np.ndarray) -> np.ndarray:
        """A continuation pose (in its own world and scale) in the earlier run's world."""
        T = self.T_start_cworld @ np.asarray(T_cworld_base, float)
        T[:3, 3] *= self.scale
        return self.T_world_start @ T


def seam(base: JournalContents, first_frame: int, records: list[FrameRecord], online: list[np.ndarray],
         T_cworld_start: np.ndarray | None = None) -> Seam:
    """How a continuation (its stats rows and causal poses) joins ``base`` at frame ``first_frame``: its pose
    there (``T_cworld_start``, default the identity: it started there) goes to the pose ``base`` ends with for that
    frame (its final smoothed pose when it is a final keyframe), and, when the run has no metric cue, its
    translations are scaled by :func:`overlap_scale` (on its frames from ``first_frame`` on)."""
    n = sum(1 for r in base.records if r.frame_index <= first_frame)
    if first_frame in base.final_keyframes:
        T_start = base.final_keyframes[first_frame][1]
    elif n:
        T_start = resumed_trajectory(base).T_world_base[n - 1]
    else:
        T_start = np.eye(4)
    T_inv = inv_T(np.eye(4) if T_cworld_start is None else np.asarray(T_cworld_start, float))
    from_k = [i for i, r in enumerate(records) if r.frame_index >= first_frame]
    s = 1.0
    if not base.metric_cue and n and from_k:
        T_inv_online = inv_T(online[from_k[0]])  # the causal poses relative to the causal pose at the seam
        s = overlap_scale(base, n - 1, [records[i] for i in from_k], [T_inv_online @ online[i] for i in from_k])
    return Seam(first_frame, n, np.asarray(T_start, float), T_inv, s)


def overlap_scale(base: JournalContents, row: int, records: list[FrameRecord], online: list[np.ndarray]) -> float:
    """The scale of a continuation starting at ``base``'s row ``row``, from the frames both ran (the earlier run's
    journaled frames after it): the least-squares factor taking the continuation's keyframe positions (linearly
    interpolated in time; its world is the base at its first frame) to the earlier run's causal keyframe
    positions relative to that frame. 1 when they share less than two keyframes' motion."""
    def keyframes(recs, poses):
        rows = [i for i, r in enumerate(recs) if r.is_keyframe and r.backend_status]
        return np.asarray([recs[i].timestamp for i in rows]), np.asarray([poses[i][:3, 3] for i in rows])

    T_row_world = inv_T(base.online[row])
    t_b, p_b = keyframes(base.records[row + 1:], [T_row_world @ T for T in base.online[row + 1:]])
    t_c, p_c = keyframes(records, online)
    if len(t_c) < 2 or len(t_b) < 2:
        return 1.0
    inside = (t_b >= t_c[0]) & (t_b <= t_c[-1])
    p_i = np.stack([np.interp(t_b[inside], t_c, p_c[:, a]) for a in range(3)], axis=1)
    den = float(np.sum(p_i * p_i))
    if int(inside.sum()) < 2 or den < 1e-12:
        return 1.0
    return float(np.sum(p_b[inside] * p_i)) / den


def continued(base: JournalContents, seg: JournalContents) -> JournalContents:
    """``base`` continued by the segment ``seg`` (its frames after its seam frame), in ``base``'s world."""
    k = int(seg.header.get("seam_frame", seg.first_frame))
    rows = [i for i, r in enumerate(seg.records) if r.frame_index == k]
    if not rows or not base.records or seg.records[-1].frame_index < base.records[-1].frame_index:
        # stopped before it got as far as the run it continues: nothing of it is kept (a later one starts again)
        return dataclasses.replace(base, n_bad_lines=base.n_bad_lines + seg.n_bad_lines)
    sm = seam(base, k, seg.records, seg.online, resumed_trajectory(seg).T_world_base[rows[0]])
    keep = [i for i, r in enumerate(seg.records) if r.frame_index > sm.first_frame]
    n = sm.n_prefix
    finals = {k: v for k, v in base.final_keyframes.items() if k <= sm.first_frame}
    if n and sm.first_frame not in finals:  # the continuation's first keyframe: its pose is fixed (the seam)
        finals[sm.first_frame] = (base.records[n - 1].timestamp, sm.T_world_start)
    finals.update({k: (t, sm.place(T)) for k, (t, T) in seg.final_keyframes.items() if k > sm.first_frame})
    return JournalContents(
        header=base.header, records=base.records[:n] + [seg.records[i] for i in keep],
        online=base.online[:n] + [sm.place(seg.online[i]) for i in keep],
        wheel_m=base.wheel_m[:n] + [seg.wheel_m[i] for i in keep], final_keyframes=finals, end=seg.end,
        n_bad_lines=base.n_bad_lines + seg.n_bad_lines, resumed_from=[*base.resumed_from, sm.first_frame])


def _parse(line: str) -> object:
    try:
        return json.loads(line)
    except ValueError:
        return None


def resumed_trajectory(j: JournalContents) -> Trajectory:
    """One pose per journaled frame: the final keyframes as smoothed, the frames between two of them placed along
    their segment (by wheel distance when the run used wheels, else by time) as the finished run places them, and
    the frames after the last final keyframe moved on from it by their causal poses' relative motion."""
    if not j.records:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    index_of = {r.frame_index: i for i, r in enumerate(j.records)}
    kfs = sorted((index_of[k], t, T) for k, (t, T) in j.final_keyframes.items() if k in index_of)
    if not kfs:
        return Trajectory(j.timestamps, np.stack(j.online))
    poses = []
    rows = [row for row, _, _ in kfs]
    for i, rec in enumerate(j.records):
        pos = int(np.searchsorted(rows, i, side="right")) - 1
        if pos < 0:
            poses.append(kfs[0][2])
        elif kfs[pos][0] == i:
            poses.append(kfs[pos][2])
        elif pos == len(kfs) - 1:
            row, _, T_kf = kfs[pos]
            poses.append(T_kf @ inv_T(j.online[row]) @ j.online[i])
        else:
            (r0, t0, T0), (r1, t1, T1) = kfs[pos], kfs[pos + 1]
            poses.append(interpolate_T(T0, T1, _fraction(j, i, r0, r1, rec.timestamp, t0, t1)))
    return Trajectory(j.timestamps, np.stack(poses))


def _fraction(j: JournalContents, i: int, r0: int, r1: int, t: float, t0: float, t1: float) -> float:
    """How far frame row ``i`` is along the keyframe segment ``r0 -> r1`` (the finished run's rule: by wheel distance,
    by time without wheels or where the back end took the segment's wheel step for slip)."""
    s = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
    w, w1 = j.wheel_m[i], j.wheel_m[r1]
    consecutive = not any(r.is_keyframe for r in j.records[r0 + 1:r1])
    if consecutive and not j.records[r1].wheel_slip and w is not None and w1 is not None and w1 > 1e-3:
        s = w / w1
    return float(np.clip(s, 0.0, 1.0)) if math.isfinite(s) else 0.0


def last_final_frame(j: JournalContents) -> int | None:
    """Index (in the journal's frame order) of the last frame at or before the last final keyframe."""
    rows = [i for i, r in enumerate(j.records) if r.frame_index in j.final_keyframes]
    return max(rows) if rows else None
