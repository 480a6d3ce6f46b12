"""Front end: tracks -> undistorted observations, RANSAC outlier rejection, keyframes, gates.

Per frame: track features (persistent ids), undistort them, reject outliers with an
essential-matrix RANSAC against the last keyframe (rejected tracks end), measure parallax,
decide whether this frame is a keyframe, and run the quality gates on keyframe candidates.

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

import time
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import CameraModel
from ..config import FrontendConfig, GateConfig, KeyframeConfig, TrackerKind
from ..types import Frame, FrontendOutput, GateOutcome, KeyframeReason
from .tracker import KLTTracker, ORBTracker, cell_counts

# Fewest tracks shared with the last keyframe for a two-view geometry, or for judging a standstill.
MIN_COMMON_TRACKS = 8
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
        cells = cv2.resize(image, GAIN_CELLS, interpolation=cv2.INTER_AREA).astype(np.float64)
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


@dataclass
class TwoViewResult:
    inlier_mask: np.ndarray  # (N,) bool, over the common tracks
    E: np.ndarray | None = None
    R_cur_kf: np.ndarray | None = None  # rotation taking kf-camera vectors into the current camera
    t_cur_kf: np.ndarray | None = None  # unit translation direction (current camera frame)
    cheirality_ratio: float = 1.0
    rot_comp_parallax_px: float = 0.0


def essential_ransac(xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float, threshold_px: float,
                     confidence: float) -> TwoViewResult:
    """Essential matrix by USAC (RANSAC family) between normalised points; marks the outliers."""
    n = len(xn_kf)
    if n < 8:
        return TwoViewResult(np.ones(n, bool))
    E, mask = cv2.findEssentialMat(xn_kf, xn_cur, np.eye(3), method=cv2.USAC_DEFAULT, prob=confidence,
                                   threshold=threshold_px / focal)
    if E is None or mask is None or E.shape != (3, 3):
        return TwoViewResult(np.ones(n, bool))
    return TwoViewResult(mask.ravel().astype(bool), E)


def recover_relative_pose(res: TwoViewResult, xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float) -> TwoViewResult:
    """Relative pose from E with the cheirality check, and the rotation-compensated parallax."""
    inl = res.inlier_mask
    if res.E is None or inl.sum() < 5:
        return res
    _, R, t, _ = cv2.recoverPose(res.E, xn_kf[inl], xn_cur[inl], np.eye(3))
    res.R_cur_kf, res.t_cur_kf = R, t.ravel()
    res.cheirality_ratio = cheirality_share(R, t.ravel(), xn_kf[inl], xn_cur[inl])
    res.rot_comp_parallax_px = rotation_compensated_parallax(xn_kf[inl], xn_cur[inl], focal)
    return res


def rotation_compensated_parallax(xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float) -> float:
    """Median angle (as pixels at the focal length) left after the best pure rotation.

    The rotation is fitted to the bearing vectors directly (orthogonal Procrustes), so the
    measure does not depend on decomposing E, which is degenerate without translation.
    """
    a = np.concatenate([xn_kf, np.ones((len(xn_kf), 1))], axis=1)
    b = np.concatenate([xn_cur, np.ones((len(xn_cur), 1))], axis=1)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt  # b ~ R a
    cosang = np.clip(np.einsum("ij,ij->i", a @ R.T, b), -1.0, 1.0)
    return float(np.median(np.arccos(cosang)) * focal)


def cheirality_share(R: np.ndarray, t: np.ndarray, xn_kf: np.ndarray, xn_cur: np.ndarray,
                     min_angle_deg: float = 0.3) -> float:
    """Share of triangulable correspondences (ray angle above ``min_angle_deg``) that lie in
    front of both cameras. Points too far to triangulate count neither way, so a scene of
    mostly distant points (a highway) is not mistaken for a cheirality failure."""
    a = np.concatenate([xn_kf, np.ones((len(xn_kf), 1))], axis=1) @ R.T  # kf rays in the current frame
    b = np.concatenate([xn_cur, np.ones((len(xn_cur), 1))], axis=1)
    # Solve l_b * b - l_a * a = t for the two depths, per point (2x2 normal equations).
    aa = np.einsum("ij,ij->i", a, a)
    bb = np.einsum("ij,ij->i", b, b)
    ab = np.einsum("ij,ij->i", a, b)
    at = a @ t
    bt = b @ t
    det = aa * bb - ab * ab
    cos = ab / np.sqrt(aa * bb)
    usable = (det > 1e-12) & (cos < np.cos(np.radians(min_angle_deg)))
    if not usable.any():
        return 1.0
    la = (ab * bt - bb * at) / np.where(usable, det, 1.0)
    lb = (aa * bt - ab * at) / np.where(usable, det, 1.0)
    good = (la > 0) & (lb > 0) & usable
    return float(good.sum()) / float(usable.sum())


def two_view_geometry(xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float, threshold_px: float,
                      confidence: float) -> TwoViewResult:
    """RANSAC and relative pose in one call."""
    return recover_relative_pose(essential_ransac(xn_kf, xn_cur, focal, threshold_px, confidence), xn_kf, xn_cur, focal)


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


class Frontend:
    """Stateful front end; one call to :meth:`process` per frame."""

    def __init__(
        self,
        camera: CameraModel,
        cfg: FrontendConfig,
        kf_cfg: KeyframeConfig,
        gate_cfg: GateConfig,
        static_mask: np.ndarray | None = None,
    ):
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
        self.kf_time = 0.0
        self.focal = 0.5 * (camera.fx + camera.fy)

    def _mask(self, frame: Frame) -> np.ndarray | None:
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
        image = frame.image
        if self.clahe is not None:
            image = self.clahe.apply(image)
        elif self.gain is not None:
            image = self.gain(image)
        tracks = self.tracker.track(image, self._mask(frame))
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
        out_pixels = np.zeros((0, 2))
        parallax = 0.0
        two_view = None
        kf_pair = None
        n_common = 0
        if self.kf_ids is not None and self.kf_xn is not None and len(tracks.ids):
            common, i_cur, i_kf = np.intersect1d(tracks.ids, self.kf_ids, return_indices=True)
            n_common = len(common)
            kf_xn = self.kf_xn
            if n_common:
                d = (xn[i_cur] - kf_xn[i_kf]) * self.focal
                parallax = float(np.median(np.linalg.norm(d, axis=1)))
            if n_common >= MIN_COMMON_TRACKS and parallax > 0.5:
                two_view = essential_ransac(
                    kf_xn[i_kf], xn[i_cur], self.focal, self.cfg.ransac_threshold_px, self.cfg.ransac_confidence
                )
                kf_pair = (kf_xn[i_kf], xn[i_cur])
                bad_ids = common[~two_view.inlier_mask]
                if len(bad_ids):
                    bad = np.isin(tracks.ids, bad_ids)
                    out_pixels = tracks.pixels[bad]
                    self.tracker.drop(bad_ids)
                    keep = ~bad
                    tracks.ids, tracks.pixels, tracks.ages = tracks.ids[keep], tracks.pixels[keep], tracks.ages[keep]
                    xn = xn[keep]
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
        )
        if two_view is not None:
            out.inlier_ratio = float(two_view.inlier_mask.mean())
        reason = (KeyframeReason.FIRST if self.kf_ids is None
                  else self._keyframe_reason(out, n_common, odom_motion, force_keyframe))
        if reason not in (KeyframeReason.NONE, KeyframeReason.FIRST) and two_view is not None and kf_pair is not None:
            # Pose recovery (cheirality, rotation-compensated parallax) only where the gates need it.
            recover_relative_pose(two_view, kf_pair[0], kf_pair[1], self.focal)
            out.cheirality_ratio = two_view.cheirality_ratio
            out.rot_comp_parallax_px = two_view.rot_comp_parallax_px
            out.R_cam_kf_cam = two_view.R_cur_kf
            out.t_dir_kf = two_view.t_cur_kf
        self._decide_keyframe(out, reason)
        if out.is_keyframe:
            self.kf_ids = out.track_ids.copy()
            self.kf_xn = xn.copy()
            self.kf_time = frame.timestamp
        out.frontend_ms = (time.perf_counter() - t0) * 1000.0
        return out

    def _keyframe_reason(
        self, out: FrontendOutput, n_common: int, odom_motion: tuple[float, float] | None, force: bool
    ) -> KeyframeReason:
        kc = self.kf_cfg
        tracked_ratio = n_common / max(len(self.kf_ids) if self.kf_ids is not None else 0, 1)
        wheels_still = odom_motion is None or (
            odom_motion[0] < kc.standstill_distance_m and odom_motion[1] < kc.standstill_rotation_rad
        )
        # Parallax says "still" only over tracks the keyframe shares with this frame: with none left (every
        # track lost at once: a sudden occlusion, a light switched) it is undefined, not zero, and the loss
        # must make a keyframe, or the keyframe reference is never renewed and no keyframe follows for the
        # rest of a run without wheels.
        out.standstill = n_common >= MIN_COMMON_TRACKS and out.parallax_px < kc.standstill_parallax_px \
            and wheels_still
        if force:
            return KeyframeReason.LAST
        if out.standstill:
            return KeyframeReason.NONE
        if out.parallax_px >= kc.min_parallax_px:
            return KeyframeReason.PARALLAX
        if tracked_ratio < kc.min_tracked_ratio:
            return KeyframeReason.TRACK_LOSS
        if out.timestamp - self.kf_time >= kc.max_interval_s:
            return KeyframeReason.INTERVAL
        return KeyframeReason.NONE

    def _decide_keyframe(self, out: FrontendOutput, reason: KeyframeReason) -> None:
        """Mark the frame a keyframe for ``reason`` and run the quality gates on it."""
        gc = self.gate_cfg
        if reason is KeyframeReason.FIRST:
            if len(out.track_ids) >= gc.min_features:
                out.is_keyframe, out.keyframe_reason = True, KeyframeReason.FIRST
                out.gate = GateOutcome.PASS
            else:
                out.gate = GateOutcome.FEW_FEATURES
            return
        if reason is KeyframeReason.NONE:
            return
        out.is_keyframe, out.keyframe_reason = True, reason
        # Quality gates on the candidate.
        if len(out.track_ids) < gc.min_features:
            out.gate, out.vision_ok = GateOutcome.FEW_FEATURES, False
        elif out.spread < gc.min_spread:
            out.gate, out.vision_ok = GateOutcome.POOR_SPREAD, False
        elif out.inlier_ratio < gc.min_inlier_ratio:
            out.gate, out.vision_ok = GateOutcome.LOW_INLIERS, False
        elif out.rot_comp_parallax_px < gc.min_parallax_px:
            # Rotation-only or tiny motion: existing landmarks still constrain the pose. The back end
            # still lets tracks whose own rays diverge enough (distant scenes, older tracks) become
            # landmarks; a pure spin gives none (each is checked for its triangulation angle).
            out.gate, out.vision_ok = GateOutcome.LOW_PARALLAX, True
        elif out.cheirality_ratio < gc.min_cheirality_ratio:
            out.gate, out.vision_ok = GateOutcome.CHEIRALITY, False
        else:
            out.gate = GateOutcome.PASS
