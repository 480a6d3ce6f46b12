"""Streams a run to Rerun (live viewer, web viewer, or an .rrd recording).

Entity layout (world is z up, like the robot base):

* ``world/estimate/online``   the causal per-frame estimate (``FrameEstimate.T_world_base``), revealed with time
* ``world/estimate/base``     the current causal pose; ``.../cam`` the camera frustum with the image and the
  tracked features (coloured by age, RANSAC outliers red, short tails as arrows)
* ``world/estimate/keyframes`` keyframe positions as estimated when each keyframe was added
* ``world/window``            the fixed-lag window's keyframes as smoothed now; ``world/landmarks`` its landmarks
* ``world/final``             the final smoothed trajectory (one pose per frame), logged when the run ends
* ``world/groundtruth``, ``world/wheel_odometry``  references, revealed with time like the estimate
* ``plots/{counts,ms,px,ratios}/*``  one plot view per unit; ``states/*`` gate outcome, back-end status and
  keyframe reason per keyframe (a state timeline)
* ``log``                     text log: keyframes, gate failures, resets, skipped frames, odometry gaps
* ``legend``                  markdown: what each colour means

Timelines: ``frame`` (index) and ``time`` (the sequence clock; the default timeline).

Cost: the camera image is JPEG-compressed (``viz.jpeg_quality``); scalars are buffered and sent as
columns every few frames; paths revealed with time are sent as frozen blocks plus a short growing tip,
so the data logged per frame stays flat however long the run.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..config import Config
from ..geometry import quat_from_R
from ..runtime.stage_timer import Stage, section
from ..types import BackendStatus, Frame, FrameEstimate, FrontendOutput, GateOutcome
from .opening import close_stream, open_sink
from .sinks import CLOSE_TIMEOUT_S, FLUSH_TIMEOUT_S, SinkFailed, SinkKind, bounded, check_disk, remove_partial

if TYPE_CHECKING:  # pragma: no cover
    from ..io.sequence import Sequence
    from ..runtime.pipeline import RunResult

log = logging.getLogger(__name__)

RGB = tuple[int, int, int]

# 3D colours: saturated mid-luminance hues that read on the viewer's dark and light themes.
ESTIMATE_RGB: RGB = (31, 119, 230)  # blue: causal estimate, one pose per frame
KEYFRAME_RGB: RGB = (150, 70, 210)  # purple: keyframes as estimated when added
WINDOW_RGB: RGB = (225, 40, 160)  # magenta: the smoother's current window
FINAL_RGB: RGB = (215, 48, 39)  # red: final smoothed trajectory
GROUNDTRUTH_RGB: RGB = (0, 158, 115)  # green: ground truth
WHEELS_RGB: RGB = (230, 159, 0)  # amber: wheel odometry alone
LANDMARK_RGB: RGB = (120, 120, 135)  # grey: landmarks
FRUSTUM_RGB: RGB = (31, 119, 230)
# Camera overlays.
TRACK_YOUNG_RGB: RGB = (60, 120, 255)
TRACK_OLD_RGB: RGB = (230, 230, 40)
OUTLIER_RGB: RGB = (255, 40, 40)
TAIL_RGB: RGB = (90, 200, 255)
# Plot series: no two alike within a view.
SERIES_RGB: tuple[RGB, ...] = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40))

GATE_RGB: dict[GateOutcome, RGB] = {
    GateOutcome.PASS: (44, 160, 44),
    GateOutcome.LOW_PARALLAX: (255, 127, 14),
    GateOutcome.LOW_INLIERS: (214, 39, 40),
    GateOutcome.CHEIRALITY: (148, 103, 189),
    GateOutcome.FEW_FEATURES: (140, 86, 75),
    GateOutcome.POOR_SPREAD: (227, 119, 194),
    GateOutcome.NOT_EVALUATED: (127, 127, 127),
}
STATUS_RGB: dict[BackendStatus, RGB] = {
    BackendStatus.OK: (44, 160, 44),
    BackendStatus.INIT: (31, 119, 180),
    BackendStatus.ODOMETRY_FALLBACK: (255, 127, 14),
    BackendStatus.RECOVERED: (214, 39, 40),
}


@dataclass(frozen=True)
class Series:
    """One plotted quantity: entity under ``plots/<unit>/``, label, colour."""

    unit: str
    key: str
    label: str
    color: RGB

    @property
    def entity(self) -> str:
        return f"plots/{self.unit}/{self.key}"


# unit -> (view title, series); one plot view each, so every view has one y-axis unit.
PLOT_UNITS: dict[str, tuple[str, tuple[Series, ...]]] = {}


def _register(unit: str, title: str, series: list[tuple[str, str]]) -> None:
    PLOT_UNITS[unit] = (title, tuple(Series(unit, k, lbl, SERIES_RGB[i]) for i, (k, lbl) in enumerate(series)))


_register("counts", "counts", [("tracked", "tracked (inliers)"), ("outliers", "RANSAC outliers"),
                               ("detected", "new detections"), ("landmarks", "landmarks in window")])
_register("ms", "milliseconds", [("frontend", "front end"), ("backend", "back end (keyframes)"),
                                 ("latency", "frame in -> pose out")])
_register("px", "pixels", [("parallax", "median parallax"), ("parallax_rot_comp", "parallax, rotation removed"),
                           ("reprojection_rms", "reprojection RMS")])
_register("ratios", "ratios", [("inliers", "inlier ratio"), ("cheirality", "cheirality ratio"),
                               ("spread", "feature spread")])

CAM_PATH = "world/estimate/base/cam"
SCALAR_FLUSH_FRAMES = 10  # scalars and path tips are sent every this many frames (and at the end)
REVEAL_BLOCK = 50  # points per frozen block of a path revealed with time
EPOCH_THRESHOLD_S = 1e8  # timestamps above this are taken as Unix time (shown as dates)
QUEUE_FRAMES = 32  # frames the logging thread may lag behind the run before log_frame waits
WORKER_JOIN_S = 30.0  # finish waits at most this for the logging thread to empty its queue


def _yes(flag: bool) -> str:
    # Recording properties hold booleans as words: rerun's AnyValues re-types a bool logged twice.
    return "yes" if flag else "no"


def ui(points: float) -> float:
    """A radius in screen points rather than metres (Rerun reads negative radii so)."""
    return -abs(float(points))


def _hex(c: RGB) -> str:
    return "#{:02x}{:02x}{:02x}".format(*c)


def legend_markdown() -> str:
    """The colour legend shown in the ``legend`` view."""
    rows_3d = [
        (ESTIMATE_RGB, "blue line", "estimate, causal (the pose a robot gets at each frame); frustum = current pose"),
        (KEYFRAME_RGB, "purple dots", "keyframes, as estimated when each was added"),
        (WINDOW_RGB, "magenta dots", "the smoother's window now (keyframes refined by later ones)"),
        (FINAL_RGB, "red line", "final smoothed trajectory (trajectory.txt), drawn when the run ends"),
        (GROUNDTRUTH_RGB, "green line", "ground truth"),
        (WHEELS_RGB, "amber line", "wheel odometry alone"),
        (LANDMARK_RGB, "grey dots", "landmarks in the window"),
    ]
    lines = ["## 3D (top-down; ground truth and wheels revealed with time)", "",
             "| colour | | meaning |", "|---|---|---|"]
    lines += [f"| {name} | `{_hex(c)}` | {meaning} |" for c, name, meaning in rows_3d]
    lines += ["", "## Camera", "",
              f"- dots: tracked features, **blue** (`{_hex(TRACK_YOUNG_RGB)}`) = new, **yellow** "
              f"(`{_hex(TRACK_OLD_RGB)}`) = tracked for 30+ frames",
              f"- **red** (`{_hex(OUTLIER_RGB)}`) dots: rejected by RANSAC on this frame",
              f"- **light blue** (`{_hex(TAIL_RGB)}`) arrows: each track's motion over the last frames (tails)",
              "", "## Plots and states", "",
              "One plot per unit (counts, milliseconds, pixels, ratios); the state timeline shows per keyframe "
              "the gate outcome (green = pass), the back-end status and why it became a keyframe.",
              "", "## Text log", "", "Keyframes (info), gate failures, skipped frames and odometry gaps (warn), "
              "back-end resets (error)."]
    return "\n".join(lines)


def _frame_extent(seq: Sequence, max_frames: int | None = None) -> np.ndarray | None:
    """(x, y) corners of the area the run will cover (its frames only), from ground truth or wheel odometry."""
    ts = np.asarray(seq.timestamps, float)[:max_frames]
    if not len(ts):
        return None
    if seq.groundtruth is not None and len(seq.groundtruth):
        gt = seq.groundtruth.anchored()
        inside = (gt.timestamps >= ts[0] - 1e-6) & (gt.timestamps <= ts[-1] + 1e-6)
        p = gt.positions[inside] if np.count_nonzero(inside) >= 2 else gt.positions
    elif seq.odometry is not None:
        t0 = float(ts[0])
        p = np.stack([seq.odometry.delta(t0, float(t))[:3, 3] for t in ts[:: max(1, len(ts) // 200)]])
    else:
        return None
    return np.array([p[:, :2].min(axis=0), p[:, :2].max(axis=0)])


def top_down_eye(extent: np.ndarray | None) -> rrb.EyeControls3D | None:
    """An orbit eye looking straight down on the area, x (forward at start) pointing up the screen."""
    if extent is None:
        return None
    centre = extent.mean(axis=0)
    size = float(max(np.max(extent[1] - extent[0]), 2.0))
    height = 2.0 * size
    return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=(centre[0] - 1e-3 * size, centre[1], height),
                             look_target=(centre[0], centre[1], 0.0), eye_up=(0.0, 0.0, 1.0))


LEGEND_ROWS_SHARE = 0.3  # top share of each plot kept free for its legend (y range = data top / (1 - this))


def plot_ranges(cfg: Config | None, maxima: dict[str, float] | None = None) -> dict[str, tuple[float, float]]:
    """y range per plot unit, with room at the top for the legend so that it covers no data.

    Ratios are bounded by 1; counts start from the feature and landmark budgets; ``maxima`` (the
    data's top, known when the run ends) sets the others and overrides the counts' guess."""
    tops: dict[str, float] = {"ratios": 1.05}
    if cfg is not None:
        tops["counts"] = 1.05 * max(cfg.frontend.max_features, cfg.backend.max_landmarks)
    for unit, top in (maxima or {}).items():
        if np.isfinite(top) and top > 0:
            tops[unit] = float(top)
    return {unit: (0.0, top / (1.0 - LEGEND_ROWS_SHARE)) for unit, top in tops.items()}


def blueprint(seq: Sequence | None = None, cfg: Config | None = None,
              maxima: dict[str, float] | None = None) -> rrb.Blueprint:
    """Default layout: 3D over the text log | camera over the legend | plots per unit | plots and gate states."""
    ranges = plot_ranges(cfg, maxima)
    plots = []
    for unit, (title, _series) in PLOT_UNITS.items():
        axis = rrb.ScalarAxis(range=ranges[unit], zoom_lock=False) if unit in ranges else None
        plots.append(rrb.TimeSeriesView(name=title, origin=f"plots/{unit}", axis_y=axis,
                                        plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.LeftTop, visible=True)))
    eye = top_down_eye(_frame_extent(seq, cfg.max_frames if cfg is not None else None)) if seq is not None else None
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(name="3D (top-down)", origin="world", eye_controls=eye),
                rrb.TextLogView(name="log", origin="log"),
                row_shares=[3, 1.2],
            ),
            rrb.Vertical(
                rrb.Spatial2DView(name="camera", origin=CAM_PATH),
                rrb.TextDocumentView(name="legend", origin="legend"),
                row_shares=[1, 1.3],
            ),
            rrb.Vertical(plots[0], plots[1]),
            rrb.Vertical(plots[2], plots[3], rrb.StateTimelineView(name="gate outcomes", origin="states"),
                         row_shares=[1, 1, 0.8]),
            column_shares=[3.2, 2.6, 2.1, 2.1],
        ),
        rrb.BlueprintPanel(state="hidden"),
        rrb.SelectionPanel(state="hidden"),
        rrb.TimePanel(state="collapsed", timeline="time", play_state="following"),
    )


def age_colors(ages: np.ndarray) -> np.ndarray:
    """Young tracks blue, old tracks yellow."""
    a = np.clip(ages / 30.0, 0.0, 1.0)[:, None]
    young = np.array([TRACK_YOUNG_RGB])
    old = np.array([TRACK_OLD_RGB])
    return (young * (1 - a) + old * a).astype(np.uint8)


def tail_starts(history: list[tuple[np.ndarray, np.ndarray]], ids: np.ndarray) -> np.ndarray:
    """Where each track of ``ids`` was at the oldest frame of ``history`` (per frame, oldest first: track
    ids and pixels) that holds it, (N, 2); nan for a track the history does not hold."""
    start = np.full((len(ids), 2), np.nan)
    if not history or len(ids) == 0:
        return start
    # All frames at once: a track's first occurrence is where its tail starts.
    all_ids = np.concatenate([h_ids for h_ids, _ in history])
    all_px = np.concatenate([np.asarray(h_px, float).reshape(-1, 2) for _, h_px in history])
    if len(all_ids) == 0:
        return start
    uniq, first = np.unique(all_ids, return_index=True)
    pos = np.minimum(np.searchsorted(uniq, ids), len(uniq) - 1)
    found = uniq[pos] == ids
    start[found] = all_px[first[pos[found]]]
    return start


def time_columns(frames: list[int], times: list[float], epoch: bool) -> list[rr.TimeColumn]:
    """The ``frame`` and ``time`` timelines of rows sent as columns (``time``: Unix time or the sequence clock).
    The times go to rerun as nanoseconds, rounded as ``set_time`` rounds seconds: a list of floats would be
    converted one by one in Python (a tenth of the recording thread's time)."""
    ns = np.round(np.asarray(times, dtype=np.float64) * 1e9).astype(np.int64)
    clock = (rr.TimeColumn("time", timestamp=ns.astype("datetime64[ns]")) if epoch
             else rr.TimeColumn("time", duration=ns.astype("timedelta64[ns]")))
    return [rr.TimeColumn("frame", sequence=frames), clock]


def _lengths_and_rows(rows: list[np.ndarray], width: int) -> tuple[list[int], np.ndarray]:
    lengths = [len(r) for r in rows]
    flat = np.concatenate(rows).reshape(-1, width) if rows else np.zeros((0, width))
    return lengths, flat


@dataclass
class CameraColumns:
    """The per-frame camera items (the base's pose, the JPEG image, the tracks, the RANSAC outliers, the track
    tails) buffered and sent as columns, one row a frame: the same rows as logging each frame, at a fraction of
    rerun's per-call cost (measured: a third off the logging thread's CPU on 640x480). ``batch`` frames per
    send: a few for a file, 1 for a viewer watching live."""

    batch: int
    pose: tuple[list[int], list[float], list[np.ndarray], list[np.ndarray]] = field(
        default_factory=lambda: ([], [], [], []))  # frames, times, translations, quaternions (xyzw)
    camera: tuple[list[int], list[float]] = field(default_factory=lambda: ([], []))  # frames with an image
    jpegs: list[bytes | None] = field(default_factory=list)
    tracks: tuple[list[np.ndarray], list[np.ndarray]] = field(default_factory=lambda: ([], []))  # pixels, colours
    outliers: list[np.ndarray] = field(default_factory=list)
    tails: tuple[list[int], list[float], list[np.ndarray], list[np.ndarray]] = field(
        default_factory=lambda: ([], [], [], []))  # frames, times, origins, vectors

    def add_pose(self, index: int, t: float, T_world_base: np.ndarray) -> None:
        frames, times, trans, quats = self.pose
        frames.append(index)
        times.append(t)
        trans.append(np.asarray(T_world_base[:3, 3], float))
        quats.append(quat_from_R(T_world_base[:3, :3]))

    def add_camera(self, index: int, t: float, jpeg: bytes | None, fo: FrontendOutput, tails: np.ndarray | None) -> None:
        """One frame's image (None: it failed to encode) and overlays; ``tails`` (N, 4): origins and vectors."""
        self.camera[0].append(index)
        self.camera[1].append(t)
        self.jpegs.append(jpeg)
        self.tracks[0].append(np.asarray(fo.pixels, float).reshape(-1, 2))
        self.tracks[1].append(age_colors(fo.track_ages))
        self.outliers.append(np.asarray(fo.outlier_pixels, float).reshape(-1, 2))
        if tails is not None:
            frames, times, origins, vectors = self.tails
            frames.append(index)
            times.append(t)
            origins.append(tails[:, :2])
            vectors.append(tails[:, 2:])

    @property
    def full(self) -> bool:
        return len(self.pose[0]) >= self.batch

    def send(self, rec: rr.RecordingStream, epoch: bool) -> None:
        """Send what was buffered and empty the buffer."""
        frames, times, trans, quats = self.pose
        if frames:
            rec.send_columns("world/estimate/base", indexes=time_columns(frames, times, epoch),
                             columns=rr.Transform3D.columns(translation=np.asarray(trans), quaternion=np.asarray(quats)))
        if self.camera[0]:
            self._send_camera(rec, epoch)
        for col in (*self.pose, *self.camera, self.jpegs, *self.tracks, self.outliers, *self.tails):
            col.clear()

    def _send_camera(self, rec: rr.RecordingStream, epoch: bool) -> None:
        frames, times = self.camera
        encoded = [(f, t, j) for f, t, j in zip(frames, times, self.jpegs) if j is not None]
        if encoded:
            f_img, t_img, blobs = zip(*encoded)
            rec.send_columns(f"{CAM_PATH}/image", indexes=time_columns(list(f_img), list(t_img), epoch),
                             columns=rr.EncodedImage.columns(blob=list(blobs), media_type=["image/jpeg"] * len(blobs)))
        n = len(frames)
        lengths, pixels = _lengths_and_rows(self.tracks[0], 2)
        colors = np.concatenate(self.tracks[1]).reshape(-1, 3) if n else np.zeros((0, 3), np.uint8)
        rec.send_columns(f"{CAM_PATH}/tracks", indexes=time_columns(frames, times, epoch),
                         columns=[*rr.Points2D.columns(positions=pixels, colors=colors).partition(lengths),
                                  *rr.Points2D.columns(radii=[2.0] * n)])
        lengths, pixels = _lengths_and_rows(self.outliers, 2)
        rec.send_columns(f"{CAM_PATH}/outliers", indexes=time_columns(frames, times, epoch),
                         columns=[*rr.Points2D.columns(positions=pixels).partition(lengths),
                                  *rr.Points2D.columns(colors=[OUTLIER_RGB] * n, radii=[3.0] * n)])
        f_tail, t_tail, origins, vectors = self.tails
        if f_tail:
            lengths, start = _lengths_and_rows(origins, 2)
            m = len(f_tail)
            rec.send_columns(f"{CAM_PATH}/tails", indexes=time_columns(f_tail, t_tail, epoch),
                             columns=[*rr.Arrows2D.columns(origins=start, vectors=_lengths_and_rows(vectors, 2)[1])
                                      .partition(lengths),
                                      *rr.Arrows2D.columns(colors=[TAIL_RGB] * m, radii=[0.6] * m)])


@dataclass
class RevealedPath:
    """A path drawn up to the current time: frozen blocks of ``REVEAL_BLOCK`` points, each logged once
    (entity ``<path>/b<k>``), and a growing tip (``<path>/tip``); latest-at shows exactly the part
    logged up to the time cursor, and the data logged stays O(points)."""

    entity: str
    color: RGB
    radius: float
    as_points: bool = False
    points: list[np.ndarray] = field(default_factory=list)
    frozen: int = 0  # index of the first point of the tip
    n_blocks: int = 0
    logged: int = 0  # points already sent

    def add(self, p: np.ndarray) -> None:
        self.points.append(np.asarray(p, float))

    def _archetype(self, pts: np.ndarray) -> rr.Points3D | rr.LineStrips3D:
        if self.as_points:
            return rr.Points3D(pts, colors=[self.color], radii=self.radius)
        return rr.LineStrips3D([pts], colors=[self.color], radii=self.radius)

    def flush(self, rec: rr.RecordingStream) -> None:
        """Send what was added since the last flush (at the recording's current time)."""
        n = len(self.points)
        if n == self.logged:
            return
        if n - self.frozen >= REVEAL_BLOCK:
            rec.log(f"{self.entity}/b{self.n_blocks}", self._archetype(np.asarray(self.points[self.frozen:n])))
            self.n_blocks += 1
            # Lines share the block's last point so they stay connected.
            self.frozen = n if self.as_points else n - 1
        tip = np.asarray(self.points[self.frozen:n])
        if len(tip):
            rec.log(f"{self.entity}/tip", self._archetype(tip))
        else:
            rec.log(f"{self.entity}/tip", rr.Clear(recursive=False))
        self.logged = n


class RerunLogger:
    """Streams a run to its Rerun sink (``viz.rerun``) from a thread of its own.

    The runtime calls ``log_frame`` (and ``log_message``) per frame and ``finish`` once at the end; no call
    waits without bound, and a sink that fails says so in one warning line (``self.warning``)."""

    def __init__(self, cfg: Config, seq: Sequence, recording_path: Path | None = None):
        with section(Stage.RECORDING):
            self._open(cfg, seq, recording_path)

    def _open(self, cfg: Config, seq: Sequence, recording_path: Path | None) -> None:
        t_start = time.perf_counter()
        self.cfg = cfg
        self.seq = seq
        ts = np.asarray(seq.timestamps, float)
        self._epoch = bool(len(ts) and ts[0] > EPOCH_THRESHOLD_S)
        self.warning: str | None = None  # the one warning about the sink, once given
        opened = open_sink(cfg, blueprint(seq, cfg), recording_path or (cfg.output / "recording.rrd"))
        self.rec = opened.rec
        self.sink = opened.kind
        self.path: Path | None = opened.path  # the .rrd being written, if the recording goes to a file
        self.viewer_process: subprocess.Popen | None = opened.viewer_process  # a viewer this run spawned
        if opened.warning is not None:
            self._warn(opened.warning)
        self._send_properties()
        self._log_static()
        self._init_state(ts)
        # Encoding and logging happen in a thread of their own; the run's thread only queues frames.
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_FRAMES)
        self._failed = self.sink is SinkKind.NONE
        self.worker_s = 0.0  # time spent in the logging thread
        self._worker = threading.Thread(target=self._work, name="windowvo-rerun", daemon=True)
        self._worker.start()
        # Time the run's thread spent in this logger (set-up, queueing, end), reported as a property.
        self.busy_s = time.perf_counter() - t_start

    # ------------------------------------------------------------------ the sink
    def _warn(self, text: str) -> None:
        """The one warning line about the sink (later failures of the same sink stay quiet)."""
        if self.warning is None:
            self.warning = text
            log.warning("%s", text)

    def _log_static(self) -> None:
        """What does not change with time: axes, camera, legend, plot and state styles."""
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        cam = self.seq.camera
        rec.log(CAM_PATH, rr.Transform3D(translation=cam.T_base_cam[:3, 3], mat3x3=cam.T_base_cam[:3, :3]),
                static=True)
        rec.log(CAM_PATH, rr.Pinhole(image_from_camera=cam.K, width=cam.width, height=cam.height,
                                     camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.3,
                                     color=FRUSTUM_RGB), static=True)
        rec.log("legend", rr.TextDocument(legend_markdown(), media_type=rr.MediaType.MARKDOWN), static=True)
        for _title, series in PLOT_UNITS.values():
            for s in series:
                rec.log(s.entity, rr.SeriesLines(colors=[s.color], names=[s.label], widths=[1.5]), static=True)
        rec.log("states/gate", rr.StateConfiguration(values=[g.value for g in GATE_RGB],
                                                     colors=[GATE_RGB[g] for g in GATE_RGB]), static=True)
        rec.log("states/backend", rr.StateConfiguration(values=[s.value for s in STATUS_RGB],
                                                        colors=[STATUS_RGB[s] for s in STATUS_RGB]), static=True)

    def _init_state(self, ts: np.ndarray) -> None:
        seq = self.seq
        # Sizes in screen points (negative radii), so paths read the same on a 5 m room and a 5 km drive.
        self.online = RevealedPath("world/estimate/online", ESTIMATE_RGB, ui(2.5))
        self.keyframes = RevealedPath("world/estimate/keyframes", KEYFRAME_RGB, ui(3.0), as_points=True)
        self.groundtruth = RevealedPath("world/groundtruth", GROUNDTRUTH_RGB, ui(1.0))
        self.wheels = RevealedPath("world/wheel_odometry", WHEELS_RGB, ui(1.0))
        self._paths = [self.online, self.keyframes, self.groundtruth, self.wheels]
        self._gt = seq.groundtruth.anchored() if seq.groundtruth is not None and len(seq.groundtruth) else None
        self._gt_next = 0  # next ground-truth sample to reveal
        self._t0 = float(ts[0]) if len(ts) else 0.0
        # Scalars waiting to be sent as columns: entity -> (frame indices, times, values).
        self._scalars: dict[str, tuple[list[int], list[float], list[float]]] = {}
        self._unit_values: dict[str, list[float]] = {}  # every plotted value per unit, for the final y ranges
        self._frames_since_flush = 0
        self.n_logged_frames = 0
        # Pixels of the tracks over the last few frames, for the tails: (ids, pixels) per frame.
        self._tail_history: list[tuple[np.ndarray, np.ndarray]] = []
        # The per-frame camera items, sent as columns: every few frames to a file, at once to a live viewer.
        self._camera = CameraColumns(SCALAR_FLUSH_FRAMES if self.sink is SinkKind.FILE else 1)

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                fn, args = item
                t_start = time.perf_counter()
                if not self._failed:
                    with section(Stage.RECORDING_THREAD):
                        fn(*args)
                self.worker_s += time.perf_counter() - t_start
            except Exception as err:  # the viewer must never stop the run
                self._warn(f"viz.rerun={self.cfg.viz.rerun.value}: logging failed ({type(err).__name__}: {err}); "
                           f"the rest of the run is not recorded")
                self._failed = True
            finally:
                self._queue.task_done()

    def _submit(self, fn, *args) -> None:
        t_start = time.perf_counter()
        if self._worker.is_alive():
            with section(Stage.RECORDING):
                self._queue.put((fn, args))
        self.busy_s += time.perf_counter() - t_start

    # ------------------------------------------------------------------ recording properties
    def _send_properties(self) -> None:
        seq, cfg = self.seq, self.cfg
        name = seq.name or seq.root.name
        self.rec.send_recording_name(f"windowvo: {name}")
        ts = np.asarray(seq.timestamps, float)
        n = len(ts) if cfg.max_frames is None else min(len(ts), cfg.max_frames)
        duration = float(ts[n - 1] - ts[0]) if n else 0.0
        self.rec.send_property("sequence", rr.AnyValues(
            name=name, path=str(seq.root), dataset=cfg.dataset.value, frames=n, duration_s=duration,
            start_time_s=float(ts[0]) if n else 0.0, camera=f"{seq.camera.width}x{seq.camera.height}",
            wheel_odometry=_yes(seq.odometry is not None), ground_truth=_yes(seq.groundtruth is not None)))
        import yaml

        self.rec.send_property("config", rr.AnyValues(yaml=yaml.safe_dump(cfg.to_yaml_dict(), sort_keys=False)))

    # ------------------------------------------------------------------ per frame
    def _set_time(self, index: int, t: float) -> None:
        self.rec.set_time("frame", sequence=index)
        if self._epoch:
            self.rec.set_time("time", timestamp=t)
        else:
            self.rec.set_time("time", duration=t)

    def _scalar(self, key: str, index: int, t: float, value: float) -> None:
        if not np.isfinite(value):
            return
        self._unit_values.setdefault(key.split("/")[1], []).append(float(value))
        buf = self._scalars.setdefault(key, ([], [], []))
        buf[0].append(index)
        buf[1].append(t)
        buf[2].append(float(value))

    def _reveal_references(self, t: float) -> None:
        if self._gt is not None:
            j = int(np.searchsorted(self._gt.timestamps, t + 1e-9, side="right"))
            if j > self._gt_next:
                self.groundtruth.add(self._gt.positions[j - 1])
                self._gt_next = j
        odo = self.seq.odometry
        if odo is not None:
            self.wheels.add(odo.delta(self._t0, t)[:3, 3])

    def log_frame(self, frame: Frame | None, est: FrameEstimate) -> None:
        """Log one frame. ``frame`` may be None for a skipped frame (``est.skipped``): its pose and note
        are logged, nothing from the camera. Returns at once: a thread of its own does the work."""
        self._submit(self._log_frame, frame, est)

    def _log_frame(self, frame: Frame | None, est: FrameEstimate) -> None:
        idx, t = est.frame_index, float(est.timestamp)
        rec = self.rec
        self._set_time(idx, t)
        self.n_logged_frames += 1
        self._camera.add_pose(idx, t, est.T_world_base)
        self.online.add(est.T_world_base[:3, 3])
        self._reveal_references(t)
        self._scalar("plots/ms/latency", idx, t, est.latency_ms)
        if est.skipped:
            rec.log("log", rr.TextLog(f"frame {idx} {est.note or 'skipped'}", level=rr.TextLogLevel.WARN))
        fo, bo = est.frontend, est.backend
        if fo is not None:
            self._log_frontend(frame, fo, idx, t)
        if bo is not None:
            self.keyframes.add(bo.T_world_base[:3, 3])
            order = sorted(bo.keyframe_poses)
            win = np.asarray([bo.keyframe_poses[k][:3, 3] for k in order]).reshape(-1, 3)
            rec.log("world/window", rr.Points3D(win, colors=[WINDOW_RGB], radii=ui(4.0)))
            rec.log("world/landmarks", rr.Points3D(bo.p_world_landmarks.reshape(-1, 3), colors=[LANDMARK_RGB],
                                                   radii=ui(1.5)))
            self._scalar("plots/counts/landmarks", idx, t, bo.n_landmarks)
            self._scalar("plots/px/reprojection_rms", idx, t, bo.reprojection_rms_px)
            self._scalar("plots/ms/backend", idx, t, bo.backend_ms)
            rec.log("states/backend", rr.StateChange(state=bo.status.value))
        if fo is not None and fo.is_keyframe:
            self._log_keyframe_text(idx, fo, est)
        elif est.note and not est.skipped:
            rec.log("log", rr.TextLog(f"frame {idx}: {est.note}", level=rr.TextLogLevel.WARN))
        self._frames_since_flush += 1
        if self._frames_since_flush >= SCALAR_FLUSH_FRAMES:
            self.flush()
        elif self._camera.full:
            self._camera.send(rec, self._epoch)

    def log_message(self, text: str, level: str = "WARN", frame_index: int | None = None,
                    timestamp: float | None = None) -> None:
        """A line in the text log (e.g. a skipped frame or an odometry gap the pipeline noticed)."""
        self._submit(self._log_message, text, level, frame_index, timestamp)

    def _log_message(self, text: str, level: str, frame_index: int | None, timestamp: float | None) -> None:
        if frame_index is not None and timestamp is not None:
            self._set_time(frame_index, float(timestamp))
        self.rec.log("log", rr.TextLog(text, level=level))

    def _log_frontend(self, frame: Frame | None, fo: FrontendOutput, idx: int, t: float) -> None:
        tail = self.cfg.viz.track_tail
        if tail > 1:
            self._tail_history.append((fo.track_ids, fo.pixels))
            del self._tail_history[:-tail]
        if frame is not None and idx % self.cfg.viz.image_every == 0:
            self._log_camera(frame, fo, idx, t)
        self._scalar("plots/counts/tracked", idx, t, len(fo.track_ids))
        self._scalar("plots/counts/outliers", idx, t, len(fo.outlier_pixels))
        self._scalar("plots/counts/detected", idx, t, fo.n_detected)
        self._scalar("plots/ratios/inliers", idx, t, fo.inlier_ratio)
        self._scalar("plots/ratios/cheirality", idx, t, fo.cheirality_ratio)
        self._scalar("plots/ratios/spread", idx, t, fo.spread)
        self._scalar("plots/px/parallax", idx, t, fo.parallax_px)
        self._scalar("plots/px/parallax_rot_comp", idx, t, fo.rot_comp_parallax_px)
        self._scalar("plots/ms/frontend", idx, t, fo.frontend_ms)

    def _log_keyframe_text(self, idx: int, fo: FrontendOutput, est: FrameEstimate) -> None:
        rec = self.rec
        bo = est.backend
        status = bo.status if bo is not None else None
        reason = fo.keyframe_reason.value or "forced"
        rec.log("states/gate", rr.StateChange(state=fo.gate.value))
        rec.log("states/keyframe_reason", rr.StateChange(state=reason))
        text = f"keyframe at frame {idx} ({reason}): gate {fo.gate.value}"
        if bo is not None:
            text += f", back end {bo.status.value}, {bo.n_landmarks} landmarks"
        if est.note:
            text += f"; {est.note}"
        level = rr.TextLogLevel.INFO
        if fo.gate not in (GateOutcome.PASS, GateOutcome.NOT_EVALUATED) or est.note:
            level = rr.TextLogLevel.WARN
        if status is BackendStatus.RECOVERED:
            level = rr.TextLogLevel.ERROR
        rec.log("log", rr.TextLog(text, level=level))

    def flush(self) -> None:
        """Send buffered scalars (as columns) and the revealed paths' tips."""
        rec = self.rec
        self._camera.send(rec, self._epoch)
        for key, (idx, ts, vals) in self._scalars.items():
            if not idx:
                continue
            rec.send_columns(key, indexes=time_columns(idx, ts, self._epoch),
                             columns=rr.Scalars.columns(scalars=np.asarray(vals)))
            idx.clear()
            ts.clear()
            vals.clear()
        for p in self._paths:
            p.flush(rec)
        self._frames_since_flush = 0
        if self.sink is SinkKind.FILE:
            self._check_file()
        elif self.viewer_process is not None and self.viewer_process.poll() is not None:
            self._warn(f"viz.rerun={self.cfg.viz.rerun.value}: the viewer exited during the run (code "
                       f"{self.viewer_process.returncode}); the rest of the run is not recorded")
            close_stream(self.rec)
            self.sink, self._failed = SinkKind.NONE, True

    def _check_file(self) -> None:
        """Drop the recording (delete the file, stop logging) when its disk runs short or a write failed:
        a recording must never fill the disk that the trajectory and the summary still go to."""
        assert self.path is not None
        try:
            check_disk(self.path)
            self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S)  # raises once the file writer has died
        except (SinkFailed, RuntimeError) as err:
            self._drop_file(str(err))

    def _drop_file(self, reason: str) -> None:
        close_stream(self.rec)
        remove_partial(self.path)
        self._warn(f"viz.rerun={self.cfg.viz.rerun.value}: writing {self.path} failed ({reason}); "
                   f"the recording is dropped")
        self.sink, self.path, self._failed = SinkKind.NONE, None, True

    def _log_camera(self, frame: Frame, fo: FrontendOutput, idx: int, t: float) -> None:
        ok, jpeg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.viz.jpeg_quality])
        tails = None
        if self.cfg.viz.track_tail > 1 and len(fo.track_ids):
            # Track tails as arrows from where each track was `track_tail` frames ago to where it is.
            start = tail_starts(self._tail_history, fo.track_ids)
            ok_rows = np.all(np.isfinite(start), axis=1)
            tails = np.hstack([start[ok_rows], np.asarray(fo.pixels, float)[ok_rows] - start[ok_rows]])
        self._camera.add_camera(idx, t, jpeg.tobytes() if ok else None, fo, tails)

    # ------------------------------------------------------------------ end of run
    def finish(self, result: RunResult, report=None) -> None:
        """Log the final smoothed trajectory (one pose per frame, as trajectory.txt) at the last frame's
        time, the run's numbers and the accuracy as recording properties, and close the recording."""
        t_start = time.perf_counter()
        self._submit(self._finish, result, report, t_start)
        if self._worker.is_alive():
            with contextlib.suppress(queue.Full):
                self._queue.put(None, timeout=WORKER_JOIN_S)
            self._worker.join(WORKER_JOIN_S)
        self.busy_s += time.perf_counter() - t_start
        if self._worker.is_alive():
            self._warn(f"viz.rerun={self.cfg.viz.rerun.value}: the recording's logging thread was still busy after "
                       f"{WORKER_JOIN_S:.0f} s; the end of the run is not recorded")
        with section(Stage.RECORDING):  # flushing and closing the sink
            self.close()

    def close(self) -> None:
        """Flush and close the sink, each step bounded in time (idempotent; ``finish`` calls it). A live
        viewer that does not take the data in time gets one warning; the run goes on regardless."""
        if self.sink is SinkKind.NONE and self.path is None:
            close_stream(self.rec)
            return
        sink, where = self.sink, self.path or self.cfg.viz.connect_url
        flushed = True
        if self.sink is SinkKind.FILE:
            self._check_file()
        if self.sink is not SinkKind.NONE:
            done, err = bounded(lambda: self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S), FLUSH_TIMEOUT_S + 2.0,
                                "windowvo-rerun-flush")
            flushed = done and err is None
            if not flushed:
                reason = f"not within {FLUSH_TIMEOUT_S:.0f} s" if not done else str(err)
                self._warn(f"viz.rerun={self.cfg.viz.rerun.value}: the end of the recording did not reach the "
                           f"{sink.value} ({where}): {reason}")
        if sink is not SinkKind.SERVER:  # a served recording lives as long as this process
            # After a failed flush, closing would only wait for the same sink: a short wait then.
            close_stream(self.rec, CLOSE_TIMEOUT_S if flushed else 1.0)
        self.sink = SinkKind.NONE if sink is not SinkKind.SERVER else sink

    def _finish(self, result: RunResult, report, t_start: float) -> None:
        self.flush()
        traj = result.trajectory
        if len(traj) and result.last_frame_index >= 0:
            self._set_time(result.last_frame_index, float(traj.timestamps[-1]))
            self.rec.log("world/final", rr.LineStrips3D([traj.positions], colors=[FINAL_RGB], radii=ui(1.25)))
        # The layout again, now with y ranges that leave the legends room above the data.
        # (counts: their maximum, as the landmark count can exceed the configured budgets; ms and px: the
        # 99th percentile, so one spike does not flatten the plot)
        maxima = {unit: float(np.max(v) if unit == "counts" else np.percentile(v, 99))
                  for unit, v in self._unit_values.items() if unit in ("counts", "ms", "px") and v}
        self.rec.send_blueprint(blueprint(self.seq, self.cfg, maxima), make_active=True, make_default=True)
        self.rec.send_property("run", rr.AnyValues(
            frames=result.n_frames, keyframes=result.n_keyframes, skipped_frames=result.n_skipped,
            wall_s=float(result.wall_s), fps=float(result.fps), backend_resets=result.n_resets,
            monocular=_yes(result.monocular), interrupted=_yes(result.interrupted),
            viewer_busy_s=float(self.busy_s + time.perf_counter() - t_start), viewer_thread_s=float(self.worker_s)))
        acc = getattr(report, "accuracy", None) if report is not None else None
        if acc is not None:
            # Numbers only (None = not available, e.g. the ATE SE(3) of a monocular run).
            values: dict[str, Any] = {k: float(v) for k, v in acc.as_dict().items()
                                      if isinstance(v, (int, float)) and not isinstance(v, bool)}
            values["summary"] = acc.summary()
            self.rec.send_property("accuracy", rr.AnyValues(**values))
            self.rec.log("log", rr.TextLog("accuracy: " + acc.summary(), level=rr.TextLogLevel.INFO))
