"""Front end: tracks -> undistorted observations, RANSAC outlier rejection, keyframes, gates.

Per frame: track features (persistent ids), undistort them, reject outliers with an
essential-matrix RANSAC against the last keyframe (rejected tracks end), measure parallax (and the
tracks' median motion since the last frame, ``flow_px``, for the wheel clock), decide whether this
frame is a keyframe, and run the quality gates on keyframe candidates.

Lenses: tracks are measured in the distorted image and handed on as the pixels an ideal
pinhole camera with the same K would see. A ray far off the optical axis maps to huge
pinhole coordinates (and at 90 degrees or more, a fisheye's, to none), so the image region
beyond ``frontend.max_ray_angle_deg`` is masked out: no detections there, and tracks that
move into it end. Each observation carries ``pixel_sigma_scale``, how much the undistortion
stretches one pixel of image noise at that point.

Exposure: every frame is scaled to one mean grey level before tracking (``GainNormalizer``), except
across a change in part of the view, which keeps the grey levels elsewhere (and their tracks).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import DetectionOrder, FrontendConfig, GateConfig, KeyframeConfig, TrackerKind
from ..runtime.stage_timer import Laps, Stage, section
from ..types import Frame, FrontendOutput, KeyframeReason
from .gates import MIN_COMMON_TRACKS, TrackShare, apply_gates, keyframe_reason
from .rocking import ROCKING_NOTE, RockingCheck
from .tracker import KLTTracker, ORBTracker, cell_counts
from .two_view import TwoViewResult, essential_ransac, recover_relative_pose

log = logging.getLogger(__name__)

# Gain normalisation. Exposure changes are measured on a grid of cells (columns, rows): the cells whose mean
# grey ratio to the previous frame lies within GAIN_AGREE_LOG (log) of one another agree on one; at least
# GAIN_MIN_AGREEING of the cells must. A frame whose mean moved more than GAIN_SCENE_CHANGE_LOG away from
# that is a scene change in part of the view, not an exposure change.
GAIN_CELLS = (8, 6)
GAIN_AGREE_LOG = 0.04
GAIN_MIN_AGREEING = 0.25
GAIN_SCENE_CHANGE_LOG = 0.03
# After one, the gain's offset from the plain normalisation decays by this share (in log) per frame.
GAIN_OFFSET_DECAY = 0.02


# OpenCV's INTER_AREA reduction in float32 (``cv2.resize``'s generic path, taken when the image is not a whole
# multiple of the cells) is off the exact cell mean by at most this many float32 roundings per summed pixel
# row and column (plus the weights' own roundings); AREA_MEAN_SLACK covers the float64 error of the exact means.
AREA_ROUNDINGS_EXTRA = 4
AREA_MEAN_SLACK = 1e-6
# A cell edge closer than this (in pixels) to a whole pixel gets no sliver weight in OpenCV's area tables.
AREA_SLIVER_PX = 1e-3


@dataclass(frozen=True)
class AreaTable:
    """OpenCV's INTER_AREA table along one axis (``computeResizeAreaTab``): per cell, the source pixels and their
    float32 weights in its order; and where the cells' edges fall, for the integral image."""

    pixels: tuple[np.ndarray, ...]  # per cell (K,) int64
    weights: tuple[np.ndarray, ...]  # per cell (K,) float32
    edge_index: np.ndarray  # (cells + 1,) int64: whole pixel of each edge (at most n - 1) ...
    edge_frac: np.ndarray  # (cells + 1,) float64: ... and the fraction past it
    width_px: np.ndarray  # (cells,) float64


def area_table(n: int, k: int) -> AreaTable | None:
    """n pixels into k cells, as OpenCV cuts them (``scale = 1 / (k / n)``); None when an edge sits within
    ``AREA_SLIVER_PX`` of a whole pixel without being on it (OpenCV drops that sliver; exact means would not)."""
    scale = 1.0 / (k / n)
    pixels, weights, starts = [], [], []
    for d in range(k):
        f1 = d * scale
        f2 = f1 + scale
        width = min(scale, n - f1)
        s2 = min(math.floor(f2), n - 1)
        s1 = min(math.ceil(f1), s2)
        idx, w = list(range(s1, s2)), [1.0 / width] * (s2 - s1)
        if s1 - f1 > 1e-3:
            idx, w = [s1 - 1, *idx], [(s1 - f1) / width, *w]
        if f2 - s2 > 1e-3:
            idx, w = [*idx, s2], [*w, min(f2 - s2, 1.0, width) / width]
        pixels.append(np.asarray(idx, np.int64))
        weights.append(np.asarray(w, np.float64).astype(np.float32))
        starts.append(f1)
    edges = np.minimum(np.asarray([*starts, float(n)]), float(n))
    dist = np.abs(edges - np.rint(edges))
    if np.any((dist > 1e-9) & (dist <= AREA_SLIVER_PX + 1e-9)):
        return None
    index = np.minimum(np.floor(edges).astype(np.int64), n - 1)
    return AreaTable(tuple(pixels), tuple(weights), index, edges - index, np.minimum(scale, n - edges[:-1]))


@dataclass(frozen=True)
class AreaGrid:
    """Both axes' tables of an INTER_AREA reduction and the bound on OpenCV's relative float32 error."""

    rows: AreaTable
    cols: AreaTable
    rel_error: float


@lru_cache(maxsize=8)
def area_grid(height: int, width: int, cols: int, rows: int) -> AreaGrid | None:
    """The cells' geometry for ``area_cell_means``; None where ``cv2.resize`` is used itself: a whole number
    of pixels per cell (its fast integer path, already cheap), upsampling, or edges OpenCV rounds off."""
    if (width % cols == 0 and height % rows == 0) or width < cols or height < rows:
        return None
    ys, xs = area_table(height, rows), area_table(width, cols)
    if ys is None or xs is None:
        return None
    roundings = max(map(len, ys.pixels)) + max(map(len, xs.pixels)) + AREA_ROUNDINGS_EXTRA
    return AreaGrid(ys, xs, roundings * 2.0**-24)


def opencv_area_cell(image: np.ndarray, grid: AreaGrid, r: int, c: int) -> float:
    """Cell (r, c) of ``cv2.resize(image, ..., interpolation=cv2.INTER_AREA)`` before its rounding: OpenCV's
    float32 sums in OpenCV's order (each row's weighted pixels, then the weighted rows; cumsum adds in order)."""
    ys, ws = grid.rows.pixels[r], grid.rows.weights[r]
    xs, wx = grid.cols.pixels[c], grid.cols.weights[c]
    row_sums = np.cumsum(image[np.ix_(ys, xs)].astype(np.float32) * wx, axis=1, dtype=np.float32)[:, -1]
    return float(np.cumsum(ws * row_sums, dtype=np.float32)[-1])


def area_cell_means(image: np.ndarray, cells: tuple[int, int]) -> np.ndarray:
    """``cv2.resize(image, cells, interpolation=cv2.INTER_AREA)`` of a uint8 image, as float64, bit for bit.

    OpenCV's generic area path (an image not a whole multiple of the cells, e.g. KITTI's 1226x370 into 8x6)
    costs 1.4 ms a frame; here the exact cell means come from the integral image (bilinear in the edges'
    fractions) in about 0.15 ms and are rounded as OpenCV rounds (half to even). A cell whose exact mean lies
    within OpenCV's float32 error bound (``AreaGrid.rel_error``) of a rounding boundary could round the other
    way there: such a cell (about one frame in ten has one) is summed as OpenCV sums it."""
    h, w = image.shape[:2]
    grid = area_grid(h, w, cells[0], cells[1])
    if grid is None or image.ndim != 2 or image.dtype != np.uint8:
        return cv2.resize(image, cells, interpolation=cv2.INTER_AREA).astype(np.float64)
    ii = cv2.integral(image, sdepth=cv2.CV_32S if 255 * h * w < 2**31 else cv2.CV_64F)
    ys, xs = grid.rows, grid.cols
    fy = ys.edge_frac[:, None]
    rows = ii[ys.edge_index].astype(np.float64) * (1.0 - fy) + ii[ys.edge_index + 1] * fy
    at_edges = rows[:, xs.edge_index] * (1.0 - xs.edge_frac) + rows[:, xs.edge_index + 1] * xs.edge_frac
    means = np.diff(np.diff(at_edges, axis=0), axis=1) / np.outer(ys.width_px, xs.width_px)
    rounded = np.rint(means)
    near = np.abs(np.abs(means - rounded) - 0.5) <= grid.rel_error * means + AREA_MEAN_SLACK
    for r, c in zip(*np.nonzero(near), strict=True):
        rounded[r, c] = np.rint(np.float32(opencv_area_cell(image, grid, int(r), int(c))))
    return rounded


def exposure_ratio(prev_cells: np.ndarray, cells: np.ndarray) -> float | None:
    """The brightness ratio between two frames (their cell means) that most cells agree on: an exposure
    change scales them all alike, a scene change in part of the view scatters its cells' ratios. The
    largest group of cells within ``GAIN_AGREE_LOG`` of one another, then their median; None when no
    group holds ``GAIN_MIN_AGREEING`` of the lit cells."""
    lit = (cells > 1.0) & (prev_cells > 1.0)
    if not lit.any():
        return None
    lr = np.log(cells[lit] / prev_cells[lit])
    support = (np.abs(lr[:, None] - lr[None, :]) <= GAIN_AGREE_LOG).sum(axis=1)
    best = int(np.argmax(support))
    if support[best] < GAIN_MIN_AGREEING * lr.size:
        return None
    return float(np.exp(np.median(lr[np.abs(lr - lr[best]) <= GAIN_AGREE_LOG])))


class GainNormalizer:
    """Scales every frame to one mean grey level, so exposure changes do not break KLT's brightness constancy,
    except across a scene change in part of the view.

    Scaling to the mean alone turns a bright or textured region coming into view into a gain step on
    every other pixel (a floor appearing under a blank view raised the mean 16%: every track was lost).
    So each frame's mean change is checked against the exposure change most cells of a grid agree on
    (``exposure_ratio``); when the two differ by more than ``GAIN_SCENE_CHANGE_LOG``, the gain follows the
    cells instead, and the offset this leaves from the plain normalisation decays slowly. Frames without
    such a change get exactly the plain normalisation.
    """

    def __init__(self, target_mean: float):
        self.target = target_mean
        self.offset = 1.0  # multiplies the plain gain target / mean after a scene change
        self.prev_cells: np.ndarray | None = None

    def __call__(self, image: np.ndarray) -> np.ndarray:
        cells = area_cell_means(image, GAIN_CELLS)
        prev, self.prev_cells = self.prev_cells, cells
        mean = float(cv2.mean(image)[0])
        if mean <= 1.0:
            return image
        if prev is not None:
            exposure = exposure_ratio(prev, cells)
            prev_mean = float(prev.mean())
            if exposure is not None and prev_mean > 1.0:
                scene = np.log(float(cells.mean()) / prev_mean) - np.log(exposure)
                if abs(scene) > GAIN_SCENE_CHANGE_LOG:
                    self.offset *= float(np.exp(scene))
        if self.offset != 1.0:
            self.offset = float(np.exp((1.0 - GAIN_OFFSET_DECAY) * np.log(self.offset)))
            if abs(np.log(self.offset)) < 1e-4:
                self.offset = 1.0
        return cv2.convertScaleAbs(image, alpha=self.offset * self.target / mean)


def field_of_view_mask(camera: CameraModel, max_ray_angle_deg: float) -> np.ndarray | None:
    """uint8 mask, 255 where the pixel's ray lies within ``max_ray_angle_deg`` of the optical axis.

    None when every pixel does (a normal lens with a moderate field of view).
    """
    angle = camera.ray_angle(camera.pixel_grid()).reshape(camera.height, camera.width)
    inside = angle <= np.radians(max_ray_angle_deg)
    if inside.all():
        return None
    return np.where(inside, 255, 0).astype(np.uint8)


def pixel_sigma_scale(camera: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """How much one pixel of image noise grows in the undistorted pinhole pixels, per point (N,).

    The largest singular value of the undistortion's Jacobian: 1 for a pinhole camera, about
    1/cos^2(theta) for a fisheye ray theta off the axis.
    """
    if len(pixels) == 0 or not camera.has_distortion:
        return np.ones(len(pixels))
    return np.linalg.svd(camera.undistortion_jacobian(pixels), compute_uv=False)[:, 0]


@dataclass
class VersusKeyframe:
    """What comparing a frame's tracks with the last keyframe's found (``Frontend._against_keyframe``)."""

    n_common: int = 0
    n_common_established: int = 0  # of them, tracks already established at the keyframe
    parallax_px: float = 0.0
    two_view: TwoViewResult | None = None
    kf_pair: tuple[np.ndarray, np.ndarray] | None = None  # the shared tracks' rays at the keyframe and now
    outlier_pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


class Frontend:
    """Stateful front end; one call to :meth:`process` per frame."""

    def __init__(
        self,
        camera: CameraModel,
        cfg: FrontendConfig,
        kf_cfg: KeyframeConfig,
        gate_cfg: GateConfig,
        static_mask: np.ndarray | None = None,
        rocking_switch: bool = False,
    ):
        """``rocking_switch``: rows-first detection that turns to spread once the base is found rocking
        (``RockingCheck``; with wheels and ``detection_order: auto``)."""
        self.camera = camera
        self.cfg = cfg
        self.kf_cfg = kf_cfg
        self.gate_cfg = gate_cfg
        self.tracker: KLTTracker | ORBTracker = ORBTracker(cfg) if cfg.tracker is TrackerKind.ORB else KLTTracker(cfg)
        fov = field_of_view_mask(camera, cfg.max_ray_angle_deg)
        if fov is not None:
            static_mask = fov if static_mask is None else np.minimum(static_mask, fov)
        self.static_mask = static_mask
        self.max_tan_ray_angle = float(np.tan(np.radians(cfg.max_ray_angle_deg)))
        self.clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)) if cfg.clahe else None
        self.gain = GainNormalizer(cfg.gain_target) if cfg.gain_normalization else None
        self.kf_ids: np.ndarray | None = None
        self.kf_xn: np.ndarray | None = None
        self.kf_established: np.ndarray | None = None  # the keyframe's tracks of at least keyframes.min_track_age
        self.kf_time = 0.0
        self.focal = 0.5 * (camera.fx + camera.fy)
        self._prev_ids: np.ndarray | None = None  # the last processed frame's tracks and rays (the frame-to-frame flow)
        self._prev_xn: np.ndarray | None = None
        self.rocking: RockingCheck | None = None
        self.rocking_note = ""  # set at the frame the base is found rocking, until the caller takes it
        if rocking_switch and cfg.rocking_rate_deg_s is not None:
            self.rocking = RockingCheck(camera.T_base_cam[:3, :3], self.focal, cfg.rocking_frames,
                                        cfg.rocking_rate_deg_s, cfg.ransac_threshold_px, cfg.ransac_confidence)

    def mask_of(self, frame: Frame) -> np.ndarray | None:
        """The frame's usable pixels (uint8, 0 where features are forbidden): the static mask, the field of view and
        the frame's own mask together; None: every pixel."""
        m = self.static_mask
        if frame.mask is not None:
            m = frame.mask if m is None else np.minimum(m, frame.mask)
        return m

    def spread(self, pixels: np.ndarray) -> float:
        """Share of grid cells that hold at least one feature."""
        if len(pixels) == 0:
            return 0.0
        counts = cell_counts(pixels, (self.camera.height, self.camera.width), self.cfg.grid_cols, self.cfg.grid_rows)
        return float(np.count_nonzero(counts)) / counts.size

    def process(self, frame: Frame, odom_motion: tuple[float, float] | None = None, force_keyframe: bool = False) -> FrontendOutput:
        """Track one frame. ``odom_motion`` is (distance m, |yaw| rad) since the last keyframe."""
        t0 = time.perf_counter()
        tracks, xn = self._track(frame)
        tracks, xn, vs_kf = self._against_keyframe(tracks, xn)
        lap = Laps()
        out_pixels, parallax, two_view, kf_pair, n_common = (vs_kf.outlier_pixels, vs_kf.parallax_px, vs_kf.two_view,
                                                             vs_kf.kf_pair, vs_kf.n_common)
        out = FrontendOutput(
            frame_index=frame.index,
            timestamp=frame.timestamp,
            track_ids=tracks.ids,
            pixels=tracks.pixels.astype(np.float64),
            pixels_undistorted=xn * [self.camera.fx, self.camera.fy] + [self.camera.cx, self.camera.cy],
            track_ages=tracks.ages,
            outlier_pixels=out_pixels,
            parallax_px=parallax,
            n_detected=tracks.n_detected,
            spread=self.spread(tracks.pixels),
            pixel_sigma_scale=pixel_sigma_scale(self.camera, tracks.pixels),
            flow_px=self._flow_since_last_frame(tracks.ids, xn),
        )
        lap(Stage.UNDISTORTION)  # mostly the undistorted pixels and their noise scales
        if self.rocking is not None:
            self._judge_rocking(frame.timestamp, tracks.ids, xn)
            lap(Stage.RANSAC)
        if two_view is not None:
            out.inlier_ratio = float(two_view.inlier_mask.mean())
        reason = KeyframeReason.FIRST
        if self.kf_ids is not None and self.kf_established is not None:
            share = TrackShare(n_common, len(self.kf_ids), vs_kf.n_common_established, int(self.kf_established.sum()))
            reason = keyframe_reason(out, share, self.kf_time, odom_motion, force_keyframe, self.focal, self.kf_cfg)
        if reason not in (KeyframeReason.NONE, KeyframeReason.FIRST) and two_view is not None and kf_pair is not None:
            # Pose recovery (cheirality, rotation-compensated parallax) only where the gates need it.
            recover_relative_pose(two_view, kf_pair[0], kf_pair[1], self.focal)
            out.cheirality_ratio = two_view.cheirality_ratio
            out.rot_comp_parallax_px = two_view.rot_comp_parallax_px
            out.R_cam_kf_cam = two_view.R_cur_kf
            out.t_dir_kf = two_view.t_cur_kf
        apply_gates(out, reason, self.gate_cfg)
        if out.is_keyframe:
            self.kf_ids = out.track_ids.copy()
            self.kf_xn = xn.copy()
            self.kf_established = out.track_ages >= self.kf_cfg.min_track_age
            self.kf_time = frame.timestamp
        lap(Stage.KEYFRAME)
        out.frontend_ms = (time.perf_counter() - t0) * 1000.0
        return out

    def _flow_since_last_frame(self, ids: np.ndarray, xn: np.ndarray) -> float:
        """Median image motion (pixels of an ideal pinhole camera) of the tracks shared with the last processed
        frame; nan with fewer than ``MIN_COMMON_TRACKS`` of them. It grows with the speed (over the scene's depth):
        the wheel clock compares its changes with the wheels' (``backend/wheel_clock.py``)."""
        prev_ids, prev_xn = self._prev_ids, self._prev_xn
        self._prev_ids, self._prev_xn = ids.copy(), xn.copy()
        if prev_ids is None or prev_xn is None:
            return float("nan")
        _, i_cur, i_prev = np.intersect1d(ids, prev_ids, assume_unique=True, return_indices=True)
        if len(i_cur) < MIN_COMMON_TRACKS:
            return float("nan")
        return float(np.median(np.linalg.norm(xn[i_cur] - prev_xn[i_prev], axis=1))) * self.focal

    def _judge_rocking(self, t: float, ids: np.ndarray, xn: np.ndarray) -> None:
        """Feed the rocking test; once it finds the base rocking, new corners are detected spread over the image
        (bottom rows first) from the next frame on."""
        assert self.rocking is not None
        if self.rocking.observe(t, ids, xn):
            self.cfg = self.cfg.model_copy(update={"detection_order": DetectionOrder.SPREAD})
            self.tracker.cfg = self.cfg
            self.rocking_note = (f"{ROCKING_NOTE} (vision's tilt rate {self.rocking.median_rate_deg_s:.1f} deg/s): new "
                                 "corners spread over the image")
            log.info(self.rocking_note)

    def _track(self, frame: Frame):
        """The frame's tracks (after the gain normalisation) and their normalised rays; tracks past the
        field-of-view bound end here."""
        image = frame.image
        with section(Stage.GAIN):
            if self.clahe is not None:
                image = self.clahe.apply(image)
            elif self.gain is not None:
                image = self.gain(image)
        tracks = self.tracker.track(image, self.mask_of(frame))  # times its tracking and detection itself
        lap = Laps()
        xn = self.camera.undistort_normalized(tracks.pixels)
        # The mask bounds the field of view to whole pixels; sub-pixel refinement and KLT can leave a
        # track just past its edge. End every track beyond the bound (a ray at 90 degrees or more
        # has no pinhole coordinates at all: nan).
        with np.errstate(invalid="ignore"):
            beyond = ~(np.hypot(xn[:, 0], xn[:, 1]) <= self.max_tan_ray_angle)
        if beyond.any():
            self.tracker.drop(tracks.ids[beyond])
            tracks.ids, tracks.pixels, tracks.ages = tracks.ids[~beyond], tracks.pixels[~beyond], tracks.ages[~beyond]
            xn = xn[~beyond]
        lap(Stage.UNDISTORTION)
        return tracks, xn

    def _against_keyframe(self, tracks, xn: np.ndarray):
        """Parallax and essential-matrix RANSAC of the tracks shared with the last keyframe; RANSAC's outliers
        end here. Returns the surviving tracks, their rays and what the comparison found."""
        vs = VersusKeyframe()
        lap = Laps()
        if self.kf_ids is None or self.kf_xn is None or not len(tracks.ids):
            return tracks, xn, vs
        common, i_cur, i_kf = np.intersect1d(tracks.ids, self.kf_ids, return_indices=True)
        vs.n_common = len(common)
        if self.kf_established is not None:
            vs.n_common_established = int(self.kf_established[i_kf].sum())
        kf_xn = self.kf_xn
        if vs.n_common:
            d = (xn[i_cur] - kf_xn[i_kf]) * self.focal
            vs.parallax_px = float(np.median(np.linalg.norm(d, axis=1)))
        lap(Stage.KEYFRAME)  # the parallax the keyframe decision judges
        if vs.n_common >= MIN_COMMON_TRACKS and vs.parallax_px > 0.5:
            vs.two_view = essential_ransac(
                kf_xn[i_kf], xn[i_cur], self.focal, self.cfg.ransac_threshold_px, self.cfg.ransac_confidence
            )
            vs.kf_pair = (kf_xn[i_kf], xn[i_cur])
            bad_ids = common[~vs.two_view.inlier_mask]
            if len(bad_ids):
                bad = np.isin(tracks.ids, bad_ids)
                vs.outlier_pixels = tracks.pixels[bad]
                self.tracker.drop(bad_ids)
                keep = ~bad
                tracks.ids, tracks.pixels, tracks.ages = tracks.ids[keep], tracks.pixels[keep], tracks.ages[keep]
                xn = xn[keep]
            lap(Stage.RANSAC)
        return tracks, xn, vs
