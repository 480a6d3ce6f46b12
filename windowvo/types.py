"""Typed payloads passed between the pipeline stages.

data provider --Frame--> front end --FrontendOutput--> back end --BackendOutput--> viz/outputs
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from .geometry import make_T, rot_z


@dataclass
class Frame:
    """One input image with its timestamp (seconds) and sequence index."""

    index: int
    timestamp: float
    image: np.ndarray  # uint8 grayscale, H x W
    mask: np.ndarray | None = None  # uint8, 0 where features are forbidden


class DistortionModel(str, enum.Enum):
    """Lens distortion models (OpenCV's)."""

    NONE = "none"
    RADTAN = "radtan"  # k1, k2, p1, p2[, k3]
    EQUIDISTANT = "equidistant"  # k1, k2, k3, k4 (OpenCV fisheye)


class GateOutcome(str, enum.Enum):
    """Result of the quality gates on a keyframe candidate."""

    PASS = "pass"
    LOW_PARALLAX = "low_parallax"
    LOW_INLIERS = "low_inliers"
    CHEIRALITY = "cheirality"
    FEW_FEATURES = "few_features"
    POOR_SPREAD = "poor_spread"
    NOT_EVALUATED = "not_evaluated"


class KeyframeReason(str, enum.Enum):
    NONE = ""
    FIRST = "first"
    PARALLAX = "parallax"
    TRACK_LOSS = "track_loss"
    INTERVAL = "interval"
    LAST = "last"


@dataclass
class FrontendOutput:
    """Tracked observations of one frame.

    ``track_ids[i]`` was seen at distorted pixel ``pixels[i]``, which an ideal pinhole
    camera with the same K would see at ``pixels_undistorted[i]``.
    """

    frame_index: int
    timestamp: float
    track_ids: np.ndarray  # (N,) int64
    pixels: np.ndarray  # (N, 2) distorted pixels as measured
    pixels_undistorted: np.ndarray  # (N, 2)
    track_ages: np.ndarray  # (N,) frames each track has lived
    outlier_pixels: np.ndarray  # (M, 2) tracks rejected by RANSAC on this frame
    is_keyframe: bool = False
    keyframe_reason: KeyframeReason = KeyframeReason.NONE
    gate: GateOutcome = GateOutcome.NOT_EVALUATED
    vision_ok: bool = True  # back end may use vision factors for this keyframe
    parallax_px: float = 0.0  # median parallax since the last keyframe (raw)
    rot_comp_parallax_px: float = 0.0  # median parallax after removing rotation
    inlier_ratio: float = 1.0
    cheirality_ratio: float = 1.0
    spread: float = 0.0
    R_cam_kf_cam: np.ndarray | None = None  # relative rotation last keyframe -> now (camera)
    t_dir_kf: np.ndarray | None = None  # unit translation direction (camera frame of last kf)
    n_detected: int = 0
    frontend_ms: float = 0.0
    standstill: bool = False
    flow_px: float = float("nan")  # median image motion of the tracks since the last processed frame (px)
    # (N,) how much 1 px of image noise is stretched in pixels_undistorted at each track (largest
    # singular value of the undistortion Jacobian; 1 for a pinhole). None: not computed (all 1).
    pixel_sigma_scale: np.ndarray | None = None
    # The keyframe's grey image and its usable pixels (0: masked), for the back end's floor region
    # (``backend.ground.road_region``); None: not sent (the mask: every pixel usable).
    image: np.ndarray | None = None
    image_mask: np.ndarray | None = None


@dataclass
class OdometryStep:
    """Wheel odometry between the previous keyframe and this one."""

    T_prev_cur: np.ndarray  # T_base(k-1)_base(k), as the wheels report it
    distance_m: float
    ok: bool = True  # False when odometry was missing or stale for this step


class ScaleSource(str, enum.Enum):
    """What fixes a run's metric scale."""

    WHEELS = "wheels"
    WHEELS_CALIBRATED = "wheels (online calibration)"
    GROUND_PLANE = "ground plane (camera height)"


class BackendStatus(str, enum.Enum):
    """How the back end handled a keyframe."""

    OK = "ok"
    INIT = "init"  # the first keyframe, fixed by a prior
    ODOMETRY_FALLBACK = "odometry_fallback"  # gates failed: this keyframe rests on wheel odometry
    RECOVERED = "recovered"  # the smoother failed; window restarted from the last good pose


@dataclass
class BackendOutput:
    """State of the window after processing one keyframe."""

    frame_index: int
    timestamp: float
    T_world_base: np.ndarray  # 4x4 latest keyframe estimate
    keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)  # frame index -> T_world_base
    p_world_landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    landmark_ids: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    n_landmarks: int = 0
    n_new_landmarks: int = 0
    n_vision_factors: int = 0
    reprojection_rms_px: float = float("nan")
    backend_ms: float = 0.0
    status: BackendStatus = BackendStatus.OK
    n_ground_factors: int = 0  # floor landmarks tied to the ground plane at this keyframe
    wheel_scale: float = float("nan")  # online wheel calibration after this keyframe (nan: not estimated)
    wheel_yaw_bias_per_m: float = float("nan")
    wheel_yaw_scale: float = float("nan")
    # Median change of the base's tilt between consecutive keyframes of the window (deg; nan: not judged
    # yet): how much the chassis rocks. Above ``ground.rocking_jitter_deg`` floor points are measured in a
    # level frame.
    base_rocking_deg: float = float("nan")
    level_frame: bool = False  # this keyframe's floor points were measured in the level frame
    # The floor's normal in the base frame as learnt so far (ground.mount_calibration): its tilt toward the
    # base's +x and +y in degrees; nan until enough floor planes were fitted.
    floor_tilt_x_deg: float = float("nan")
    floor_tilt_y_deg: float = float("nan")
    floor_tilt_se_deg: float = float("nan")  # its standard error
    floor_normal_learnt: bool = False  # this keyframe's floor points were measured along the learnt normal
    # Floor against wheels (backend/cue_check.py): the floor's scale over the wheels' less 1 over the latest
    # keyframes (nan: not tested), and whether the chi-square test found them agreeing (None: not tested).
    cue_disagreement: float = float("nan")
    cues_agree: bool | None = None
    # The new wheel step against the window's solution (backend/wheel_slip.py): its planar residual in its own sigmas
    # (nan: not judged), and whether it was taken for slip and its planar factor switched off (None: not judged).
    wheel_step_sigmas: float = float("nan")
    wheel_slip: bool | None = None
    # ground.road_region: this keyframe's step length measured by the floor's region over the estimate's (nan: none),
    # and the floor's pitch against the assumed one it was measured on (road_region.pitch_search_deg; nan: none).
    road_step_ratio: float = float("nan")
    road_pitch_deg: float = float("nan")
    # Keyframes before the window whose poses this update changed (frame index -> T_world_base): every one at a
    # monocular run's late metric start, when the floor first came into view and the trajectory was rescaled.
    earlier_keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)
    metric_start: bool = False  # this keyframe made a monocular run metric (the floor came into view)


@dataclass
class FrameEstimate:
    """What a robot gets for one frame, at that frame's time (causal: no later frame used).

    ``T_world_base`` is the newest keyframe estimate right after it was added, moved on to this
    frame by the wheels (without wheels: along the last keyframe step, by the frame's share of it in
    parallax; held at a standstill). The fixed-lag smoothed pose of the same frame,
    refined by later keyframes, is in the smoothed trajectory instead.
    """

    frame_index: int
    timestamp: float
    T_world_base: np.ndarray  # 4x4 causal pose of the base in world
    is_keyframe: bool = False
    skipped: bool = False  # the frame was unusable (black, duplicate, unreadable); the pose still holds
    status: BackendStatus | None = None  # back-end status when this frame was a keyframe
    latency_ms: float = 0.0  # frame in -> pose out
    frontend: FrontendOutput | None = None
    backend: BackendOutput | None = None
    note: str = ""


@dataclass
class FrameRecord:
    """Per-frame row of stats.csv."""

    frame_index: int
    timestamp: float
    n_tracked: int
    n_inliers: int
    n_detected: int
    parallax_px: float
    rot_comp_parallax_px: float
    inlier_ratio: float
    cheirality_ratio: float
    spread: float
    is_keyframe: bool
    keyframe_reason: str
    gate: str
    backend_status: str
    n_landmarks: int
    reprojection_rms_px: float
    frontend_ms: float
    backend_ms: float
    note: str = ""
    n_ground_factors: int = 0
    wheel_scale: float = float("nan")
    wheel_yaw_bias_per_m: float = float("nan")
    latency_ms: float = 0.0
    base_rocking_deg: float = float("nan")
    level_frame: bool = False
    floor_tilt_x_deg: float = float("nan")
    floor_tilt_y_deg: float = float("nan")
    floor_tilt_se_deg: float = float("nan")
    floor_normal_learnt: bool = False
    cue_disagreement: float = float("nan")  # floor scale / wheel scale - 1 over the latest keyframes (nan: untested)
    cues_agree: bool | None = None  # the chi-square test of floor against wheels (None: not tested)
    wheel_yaw_scale: float = float("nan")  # online wheel calibration's yaw scale (nan: not estimated)
    road_step_ratio: float = float("nan")  # the step's length by the floor's region over the estimate's (nan: none)
    road_pitch_deg: float = float("nan")  # the floor's pitch against the assumed one it was measured on (nan: none)
    wheel_step_sigmas: float = float("nan")  # the wheel step's planar residual at the solution, sigmas (nan: not judged)
    wheel_slip: bool | None = None  # the step was taken for slip and switched off (None: not judged)


@dataclass
class WheelCalibration:
    """Current estimate of the wheels' distance scale, yaw bias (rad per metre) and yaw scale.

    The wheels are taken to report ``scale`` times the distance driven and ``yaw_scale`` times the heading
    change plus ``yaw_bias_per_m`` times the distance."""

    scale: float = 1.0
    yaw_bias_per_m: float = 0.0
    scale_sigma: float = float("nan")
    yaw_bias_sigma: float = float("nan")
    yaw_scale: float = 1.0
    yaw_scale_sigma: float = float("nan")

    def correct(self, T_prev_cur: np.ndarray, distance: float) -> np.ndarray:
        """Wheel step with the calibration removed: what the base probably did."""
        yaw_meas = float(np.arctan2(T_prev_cur[1, 0], T_prev_cur[0, 0]))
        yaw = (yaw_meas - self.yaw_bias_per_m * distance) / max(self.yaw_scale, 1e-3)
        T = make_T(rot_z(yaw), T_prev_cur[:3, 3] / max(self.scale, 1e-3))
        T[2, 3] = 0.0
        return T
