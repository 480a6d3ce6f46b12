"""Typed, validated run configuration.

Each stage owns a parameter dataclass (pydantic model) that sits beside its algorithm in
spirit; they are gathered here so one YAML file configures a run. Loading rejects unknown
keys, wrong types and impossible values with one line that names the key.
"""

from __future__ import annotations

import enum
import logging
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .errors import ConfigError
from .types import DistortionModel
from .yamlio import safe_load_yaml

log = logging.getLogger(__name__)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, use_enum_values=False)


class DatasetKind(str, enum.Enum):
    NATIVE = "native"
    KITTI = "kitti"
    TUM = "tum"
    EUROC = "euroc"
    FOLDER = "folder"
    ROSBAG = "rosbag"  # ROS 1 .bag, or a ROS 2 bag (folder with metadata.yaml, or a .db3 / .mcap file)
    VIDEO = "video"  # a video file (mp4, mkv, avi) read with OpenCV


class TrackerKind(str, enum.Enum):
    KLT = "klt"
    ORB = "orb"


class DetectionOrder(str, enum.Enum):
    """Which grid cells new corners go to first when the detection budget is short."""

    AUTO = "auto"  # spread when the floor is the run's only scale source (no wheel odometry), rows otherwise
    ROWS = "rows"  # cell after cell, top row first: the floor's rows get what is left
    SPREAD = "spread"  # one corner per cell and round, bottom rows first: the floor's rows get their share


class RobustKind(str, enum.Enum):
    HUBER = "huber"
    CAUCHY = "cauchy"  # redescending: gross outliers (wheel slip) lose almost all weight
    NONE = "none"


def yaml_off(v):
    """An enum value ``off`` as YAML 1.1 reads a bare `off`: as false."""
    return "off" if v is False else v


class LandmarkModel(str, enum.Enum):
    """How the back end's landmarks off the floor enter the window (floor landmarks are always explicit)."""
    EXPLICIT = "explicit"  # a point state L(id) per landmark, one projection factor per observation
    SMART = "smart"  # GTSAM smart projection factors: the point is eliminated, one factor per landmark


class WheelClockMode(str, enum.Enum):
    ESTIMATE = "estimate"  # estimate the wheels' time offset online from the turns and apply it once observable
    OFF = "off"  # estimate and report it, read the wheels at the camera's times
    FIXED = "fixed"  # apply backend.odometry.time_offset_ms (still estimated and reported)


class MountCalibration(str, enum.Enum):
    """Whether the ground cue measures floor heights along the floor normal learnt in the base frame."""
    OFF = "off"  # never: the base z axis (T_base_cam as given)
    AUTO = "auto"  # once the learnt tilt is significant (a mount pitched or rolled against T_base_cam)
    ON = "on"  # always, and no floor point is tied before the normal is learnt


class RegionInterpolation(str, enum.Enum):
    """How the floor's region samples the newer image between its pixels (``ground.road_region.interpolation``)."""

    LINEAR = "linear"  # bilinear: smooths a sample by an amount that depends on where it falls between pixels
    CUBIC = "cubic"  # bicubic: less of that smoothing, so less of the bias it gives a warp's scale


class RunMode(str, enum.Enum):
    SEQUENTIAL = "sequential"  # one process, one frame after the other (tests, debugging)
    PIPELINED = "pipelined"  # the back end in a worker process beside decoding and the front end


class RerunMode(str, enum.Enum):
    OFF = "off"
    SAVE = "save"
    SPAWN = "spawn"
    CONNECT = "connect"
    SERVE = "serve"


class FrontendConfig(_Section):
    tracker: TrackerKind = Field(TrackerKind.KLT, description="feature tracker: klt (optical flow, persistent track "
                                                              "ids) or orb (descriptor matching)")
    max_features: int = Field(200, gt=8, le=5000, description="live tracks kept")
    grid_cols: int = Field(8, ge=1, le=64, description="detection grid columns (new corners only in cells short of "
                                                       "tracks)")
    grid_rows: int = Field(6, ge=1, le=64, description="detection grid rows")
    min_distance_px: float = Field(12.0, gt=0, description="minimum distance between two corners")
    quality_level: float = Field(0.01, gt=0, lt=1, description="Shi-Tomasi corner quality, relative to the best corner "
                                                               "of the cell")
    klt_window_px: int = Field(9, ge=5, le=101, description="KLT window size")
    klt_levels: int = Field(3, ge=0, le=8, description="KLT pyramid levels")
    klt_highpass_px: int = Field(0, ge=0, le=201, description="place each KLT match (forward and backward, after "
                                 "the pyramid's search on the images) on the finest level of the images less their "
                                 "local means over this box (px, wider than klt_window_px): the match then assumes "
                                 "brightness constancy only up to a locally linear change, such as a polished "
                                 "floor's sheen that moves with the view (warehouses: 21; docs/scale_suite.md). "
                                 "0 (default): the images only")
    forward_backward_px: float = Field(0.5, gt=0, description="max forward-backward KLT error; tracks above it end")
    klt_max_residual: float = Field(8.0, gt=0, description="max KLT patch residual (mean absolute grey difference); "
                                                           "ends tracks on deforming patches")
    ransac_threshold_px: float = Field(0.5, gt=0, description="essential-matrix RANSAC threshold")
    ransac_confidence: float = Field(0.999, gt=0.5, lt=1, description="essential-matrix RANSAC confidence")
    clahe: bool = Field(False, description="contrast-limited histogram equalisation before tracking (dim scenes)")
    gain_normalization: bool = Field(True, description="scale every frame to one mean intensity before tracking "
                                                       "(exposure steps), except across a change in part of the "
                                                       "view (the grey levels outside it are kept)")
    gain_target: float = Field(110.0, gt=0, le=255, description="mean grey level that gain normalisation "
                               "scales every frame to")
    max_ray_angle_deg: float = Field(75.0, gt=0, lt=90, description="field-of-view bound: image regions and "
                                     "tracks whose ray is further off the optical axis are not used")
    mask: Path | None = Field(None, description="static mask image, white = features allowed (e.g. to hide the robot's "
                                                "body); relative to the config file")
    mask_folder: Path | None = Field(None, description="per-frame masks with the images' file names (white = allowed); "
                                                       "relative to the config file")
    border_px: int = Field(8, ge=0, description="no corners closer than this to the image border")
    detection_order: DetectionOrder = Field(DetectionOrder.AUTO, description="where new corners go first when the "
                                            "budget is short: rows (cell after cell, top row first), spread (one "
                                            "per cell and round, bottom rows first: the floor gets its share), "
                                            "auto (spread without wheel odometry, where the floor is the only "
                                            "scale source; with it rows, or spread when the base rocks on its "
                                            "suspension: rocking_rate_deg_s)")
    rocking_rate_deg_s: float | None = Field(
        4.0, gt=0, description="with wheel odometry and detection_order auto: vision's tilt rate (rotation about the "
        "base's horizontal axes between frames at least 45 ms apart, median over the run's first rocking_frames such "
        "pairs that move) above which the base is taken to rock on its suspension, and new corners spread over the "
        "image (bottom rows first) for the whole run (its points then measure each keyframe's tilt against the "
        "floor); measured: level rendered runs 0.04-0.15 deg/s, KITTI 0.4-1.9, rendered suspensions 5.3-27. null: "
        "rows always")
    rocking_frames: int = Field(8, ge=3, le=200, description="pairs of frames that move (median track motion of 1 px "
                                "or more) the rocking test of rocking_rate_deg_s judges, at the start of the run")

    @model_validator(mode="after")
    def _highpass_wider_than_window(self) -> FrontendConfig:
        if 0 < self.klt_highpass_px <= self.klt_window_px:
            raise ValueError(f"frontend.klt_highpass_px ({self.klt_highpass_px}) must be 0 (off) or wider than "
                             f"frontend.klt_window_px ({self.klt_window_px}): a box within the KLT window takes the "
                             "texture it tracks")
        return self


class KeyframeConfig(_Section):
    min_parallax_px: float = Field(20.0, gt=0, description="new keyframe when the median parallax to the last keyframe "
                                                           "exceeds this (pixels; see keyframes.parallax_focal_px)")
    min_tracked_ratio: float = Field(0.6, gt=0, lt=1, description="... or when fewer than this share of the keyframe's "
                                                                  "tracks survive (of those keyframes.min_track_age "
                                                                  "old)")
    max_interval_s: float = Field(1.0, gt=0, description="... or after this long (never while standing still)")
    parallax_focal_px: float | None = Field(
        None, gt=0, description="a focal length (px) makes min_parallax_px an angle, min_parallax_px / "
        "parallax_focal_px (340: 20 px is 3.4 deg, 41.6 px at KITTI's 707 px; fewer keyframes in fast turns, worse "
        "without wheels: docs/performance.md, Keyframes by information); null: pixels of the camera")
    min_track_age: int = Field(0, ge=0, description="track loss counts only the keyframe's tracks at least this "
                               "many frames old when it was taken (1: fresh corners lost at once, as in fast forward "
                               "motion, make no keyframe; fewer keyframes but fewer landmarks: see docs/performance.md, "
                               "Keyframes by information; with backend.ground.road_region on, the default, a "
                               "keyframe every other frame cost the KITTI 06 excerpt 0.072 -> 0.491 m, so use it with "
                               "the region off); 0: all of them")
    standstill_parallax_px: float = Field(1.0, ge=0, description="standing still: median parallax below this ...")
    standstill_distance_m: float = Field(0.01, ge=0, description="... and wheel distance since the keyframe below this "
                                                                 "...")
    standstill_rotation_rad: float = Field(0.005, ge=0, description="... and wheel rotation since the keyframe below "
                                                                    "this")


class GateConfig(_Section):
    min_parallax_px: float = Field(4.0, ge=0, description="a keyframe needs this rotation-compensated parallax (at most"
                                                          " keyframes.min_parallax_px)")
    min_inlier_ratio: float = Field(0.5, ge=0, le=1, description="a keyframe needs this share of RANSAC inliers")
    min_cheirality_ratio: float = Field(0.8, ge=0, le=1, description="a keyframe needs this share of near points in "
                                                                     "front of both cameras")
    min_features: int = Field(25, ge=5, description="a keyframe needs this many tracked features")
    min_spread: float = Field(0.2, ge=0, le=1, description="a keyframe's features must cover this share of the image")


class OdometryNoiseConfig(_Section):
    xy_sigma_per_m: float = Field(0.02, gt=0, description="wheel factor: sigma of the planar translation per metre "
                                                          "driven")
    xy_sigma_min_m: float = Field(0.005, gt=0, description="lower bound of the planar translation sigma")
    yaw_sigma_per_m: float = Field(0.01, gt=0, description="sigma of the heading change per metre driven")
    yaw_sigma_min_rad: float = Field(0.002, gt=0, description="lower bound of the heading sigma")
    z_sigma_m: float = Field(0.05, gt=0, description="sigma of the vertical motion between two keyframes")
    roll_pitch_sigma_rad: float = Field(0.05, gt=0, description="sigma of the roll and pitch change between two "
                                                                "keyframes")
    climb_sigma_per_m: float = Field(0.0, ge=0, description="a base on its wheels climbs (moves along its own z "
                                     "axis, the set-up's base frame) at a rate that changes only with the floor's "
                                     "slope and the suspension's load, not at every step: each two consecutive wheel "
                                     "steps are tied by how much the climb rate changes between them, with this sigma "
                                     "per metre driven (the climb rate itself stays free: a camera mount pitched by "
                                     "a degree against T_base_cam makes every step climb by 1.7%, which z_sigma_m "
                                     "must allow). 0 (default): off. 0.01 was measured: the scale suite's fused runs "
                                     "0.99x (rooms 0.94x, warehouses 0.93x: a flat room's height no longer drifts by "
                                     "centimetres; streets 1.06x, KITTI 1.10x); held out, rocking warehouses 0.71x, "
                                     "warehouses 0.87x, slipping rooms 1.21x, KITTI 1.02x (docs/scale_suite.md, \"The wheels' climb rate\")")
    climb_sigma_min_m: float = Field(0.005, gt=0, description="lower bound of that sigma (a base's bounce on its "
                                     "suspension)")
    robust: RobustKind = Field(RobustKind.CAUCHY, description="robust loss of the wheel factors (huber, cauchy, none); "
                                                              "cauchy lets consistent vision overrule slipping wheels")
    robust_k: float | None = Field(None, gt=0, description="threshold of the robust loss in sigmas of the 3-D planar "
                                   "residual; default: from the chi-square quantile of backend.robust_confidence")
    slip_switch: bool = Field(True, description="after each keyframe's update, a wheel step whose planar residual "
                              "at the window's solution lies beyond the switch's threshold is taken for slip or a skid: "
                              "its planar factor is removed, the window solved again without it, and the step left out "
                              "of the floor-against-wheels test (stats.csv wheel_step_sigmas, wheel_slip; the summary's "
                              "wheel_slip)")
    slip_switch_confidence: float = Field(0.9999, gt=0.5, lt=1, description="a step is taken for slip when its "
                                          "planar residual lies beyond the chi-square quantile (3-D) at this "
                                          "confidence (4.6 sigma): a switch is a hard decision, for gross errors only "
                                          "(the robust loss weighs the rest)")
    slip_switch_k: float | None = Field(None, gt=0, description="the switch's threshold in sigmas of the 3-D planar "
                                        "residual instead; default: from slip_switch_confidence")
    slip_switch_min_observations: int = Field(30, ge=0, description="a step is judged only where its keyframe holds "
                                              "at least this many projection factors: with fewer, vision does not "
                                              "constrain the step and a wrong solution would switch good wheels off")
    max_gap_s: float = Field(0.5, gt=0, description="longest gap in the wheel odometry bridged; over it the step is "
                                                    "vision only")
    max_speed_m_s: float = Field(60.0, gt=0, description="a wheel sample implying a faster motion since the previous "
                                 "one (plus 0.5 m) is a teleport: rejected with a warning, that step vision only")
    time_offset: WheelClockMode = Field(WheelClockMode.ESTIMATE, description="the wheels' clock against the camera's "
                                        "(t_wheels = t_camera + offset): estimate (from the turns and the speed changes, "
                                        "applied to the wheel readings of the factors and the standstill check once observable, "
                                        "as known at each keyframe), off (only reported) or fixed (time_offset_ms). "
                                        "A positive offset reads samples not yet arrived at a keyframe: up to "
                                        "max_gap_s past the newest one they are extrapolated at its velocity")
    time_offset_ms: float = Field(0.0, ge=-1000.0, le=1000.0, description="the wheels' known time offset to the "
                                  "camera in ms (positive: the wheels stamp an instant later than the camera); only "
                                  "with time_offset: fixed")
    time_offset_second_pass: bool = Field(True, description="with time_offset: estimate, a run of a recording "
                                          "(python -m windowvo.run, the batch, the benchmark; not the streaming "
                                          "Odometry API, which is causal) whose offset was applied part way is made "
                                          "again from its first frame with the wheels read at its final estimate "
                                          "(as time_offset: fixed): the keyframes before the estimate keep no wheel "
                                          "step read at the wrong time. The first pass's files go to OUT/first_pass/ "
                                          "(back to OUT if the second pass fails or is stopped); it costs a second "
                                          "run only where an offset was found")

    @field_validator("time_offset", mode="before")
    @classmethod
    def _yaml_off(cls, v):
        return yaml_off(v)

    @model_validator(mode="after")
    def _offset_needs_fixed(self) -> OdometryNoiseConfig:
        if self.time_offset_ms != 0.0 and self.time_offset is not WheelClockMode.FIXED:
            raise ValueError(f"backend.odometry.time_offset_ms is set but time_offset is '{self.time_offset.value}' "
                             "(set time_offset: fixed)")
        return self


class PlanarPriorConfig(_Section):
    enabled: bool = Field(True, description="soft, robust roll/pitch prior toward a level, z-up base (ground robots; "
                                            "off by default for the tum and euroc layouts)")
    sigma_rad: float = Field(0.1, gt=0, description="sigma of the roll/pitch prior")
    huber_k: float = Field(1.5, gt=0, description="Huber threshold of the roll/pitch prior, in sigmas")
    height_prior: bool = Field(False, description="soft z = 0 prior on the base (flat floor; needs enabled)")
    height_sigma_m: float = Field(0.5, gt=0, description="sigma of the height prior")


class RoadRegionConfig(_Section):
    """The floor measured by region (backend/road_region.py): each keyframe step's length from the floor's pixels."""

    enabled: bool = Field(True, description="measure each keyframe step's length by aligning the floor region of "
                          "the two keyframes' images through the floor's homography (the estimate's rotation and "
                          "direction, the camera height, the floor's pitch searched), tied as a range factor between "
                          "their poses, where the window ties fewer than max_floor_landmarks floor points; for floors "
                          "with few corners (a road, a plain warehouse floor). Costs about 35 ms of back end a "
                          "keyframe at 1226x370 (docs/scale_suite.md, The floor's region as the default)")
    near_heights: float = Field(2.0, gt=0, description="the region's near edge ahead of the camera, in camera heights")
    far_heights: float = Field(6.0, gt=0, description="its far edge, in camera heights")
    half_width_heights: float = Field(1.0, gt=0, description="its half width beside the optical axis, in camera "
                                      "heights")
    blur_px: float = Field(1.0, ge=0, le=5, description="sigma (pixels) of the Gaussian the two images are smoothed "
                           "by before the region is sampled (0: none). 0.5 was measured: the scale suite's streets better, the held-out "
                           "and ten more streets not (docs/scale_suite.md)")
    interpolation: RegionInterpolation = Field(RegionInterpolation.LINEAR, description="how the newer image is "
                                               "sampled between its pixels (the older one is read at its pixels): "
                                               "linear smooths a sample by how far it falls between pixels, which "
                                               "biases the floor's pitch and the step's length a little (rendered "
                                               "streets at ground truth's motion, docs/scale_suite.md); cubic less")
    normalise_px: float = Field(0.0, ge=0, le=50, description="each image's local contrast normalised before the "
                                "region is sampled: a pixel's difference from its neighbourhood's mean over the "
                                "neighbourhood's standard deviation (Gaussian neighbourhoods of this sigma, pixels), "
                                "so that a bright marking weighs no more than the asphalt's texture; 0: off. "
                                "Measured with interpolation cubic and blur_px 0: rendered streets' fused runs 0.3-0.6x, "
                                "the real KITTI road's 1.95x (docs/scale_suite.md)")
    normalise_floor: float = Field(2.0, gt=0, description="with normalise_px: grey levels added to the neighbourhood's "
                                   "standard deviation (flat areas' noise is not amplified beyond this)")
    step_px: int = Field(2, ge=1, le=16, description="the region's pixels are sampled every this many pixels")
    max_pixels: int = Field(2000, ge=100, description="at most this many sampled pixels (an even subsample; the "
                            "search's time is mostly per pixel: 6000 take about twice 2000's)")
    min_pixels: int = Field(300, ge=20, description="a step is measured only with at least this many region pixels "
                            "in both images")
    min_flow_px: float = Field(2.0, ge=0, description="... and when the step moves the region's pixels this far "
                               "(median; shorter steps do not tell their length)")
    min_correlation: float = Field(0.5, gt=-1, lt=1, description="... and the best alignment correlates this well "
                                   "(zero-mean normalised cross-correlation)")
    min_gradient_alignment: float = Field(0.1, ge=0, lt=1, description="a region pixel is used only when its image "
                                          "gradient's component along its motion in the image (the floor's flow "
                                          "between the keyframes) is at least this share of the gradient: a pixel on "
                                          "a lane line parallel to the motion tells nothing of the step's length and "
                                          "biases the floor's pitch search (0: every pixel). 0.1: the scale suite's "
                                          "fused runs 0.84x the 0's; with the untested steps' wait (wheels) 0.83x the "
                                          "old defaults (docs/scale_suite.md, \"Steps on an untested pitch wait for "
                                          "it with wheels, and the region's pixel selection as the default\")")
    metric_start: bool = Field(False, description="a monocular run whose first two keyframes show no floor plane "
                               "among their corners (a road: few corners on the asphalt) takes its first baseline "
                               "from the floor's region (the step between the two images through the floor's "
                               "homography: the two views' rotation and direction, its length searched on one grid over "
                               "0.03-3 camera heights), and is metric from its first keyframes "
                               "instead of from when a floor plane first passes")
    monocular_search_shifts: int = Field(2, ge=0, le=4, description="without wheels, a step whose best length "
                                         "lies at the edge of the coarse search (+42%/-30% of the estimate's step) is "
                                         "searched again on a grid moved out to that edge, at most this many times "
                                         "(2: steps 0.35x-2.9x the estimate's): a monocular run whose scale drifted "
                                         "while the floor was out of reach gets its floor's steps measured again "
                                         "instead of drifting on. With wheels never (their calibrated step bounds "
                                         "the estimate's; a step that far off is a slipping wheel, and the moved grid "
                                         "found 0.56-0.83 of the true step there: docs/scale_suite.md, \"The "
                                         "region's search moved out without wheels\"). 0: a step off by more is "
                                         "not measured")
    search_direction_deg: float = Field(1.5, ge=0, lt=20, description="the step's direction is searched within this "
                                        "many degrees sideways of the estimate's, alternately with its length, so that "
                                        "the length does not take up the direction's error (0: the estimate's)")
    tilt_ridge_deg: float = Field(0.0, ge=0, lt=5, description="on a base rocking on its suspension "
                                  "(ground.rocking_jitter_deg), a measured step's length is searched again with the "
                                  "newer camera tilted this many degrees up and down (about its x axis): a longer "
                                  "step and a camera tilted down move the floor's pixels alike (2-6% of length per "
                                  "0.1 deg), so the step is tied to the two poses along that ridge, its length "
                                  "taken at the window's tilt instead of the estimate's when it was measured "
                                  "(backend/road_region.py, ridge_factor; the steps measured on a pooled or the "
                                  "assumed pitch: not with pitch_window 1 and a pitch search). 0 (default): the "
                                  "length alone (a range factor). 0.1 was measured: the scale suite's rocking runs "
                                  "fused 0.73-0.77x but a rocking straight street 2.28x; held out, rocking "
                                  "warehouses 0.83x, streets 0.97x (worst 1.70x), rooms 1.03x (docs/scale_suite.md)")
    pitch_search_deg: float = Field(2.0, ge=0, lt=10, description="the floor's pitch against the camera is searched "
                                    "within this many degrees of the assumed one (the floor's learnt normal or the "
                                    "set-up's), jointly with the length: a road's slope ahead differs from the slope "
                                    "under the wheels, and a degree of it is 9% of length on a car's camera (0: the "
                                    "assumed pitch)")
    pitch_far_heights: float = Field(10.0, gt=0, description="the far edge of the region the pitch is searched on, in "
                                     "camera heights (the pitch shows in how the floor's image motion changes from the "
                                     "near rows to the far ones: the farther, the better; the length is measured on "
                                     "far_heights, where the floor is better resolved)")
    pitch_window: int = Field(15, ge=1, description="the floor's pitch a step is measured on: the median of the "
                              "pitches the last this many steps found (a camera's pitch against the road changes "
                              "slowly; one step's is loose along its ridge with the length), the length searched "
                              "again on it; 1: each step's own, with the length of its joint search")
    pitch_sigmas: float = Field(3.0, ge=0, description="with pitch_window above 1, the pooled pitch (the median) is "
                                "used once it lies this many standard errors (from the searches' spread) from the "
                                "assumed one, with 5 searches at least; until then the assumed pitch")
    pitch_systematic_deg: float = Field(0.0, ge=0, le=5, description="the error every pitch search shares "
                                        "(degrees): the floor's texture, the images' smoothing, a lane line at the "
                                        "region's side bias the searches alike, which their spread does not show; the "
                                        "pooled pitch's standard error in pitch_sigmas' test adds it, so that no "
                                        "number of searches claims the pitch better than this (0: their spread alone). "
                                        "0.2 was measured: the scale suite's fused streets 0.80x and floor-only "
                                        "streets 0.78x, KITTI the same, but held-out fused streets 1.07-1.13x "
                                        "(docs/scale_suite.md)")
    untested_pitch_deg: float = Field(0.0, ge=0, le=10, description="with pitch_window above 1 and no wheels, the "
                                      "floor's pitch against the assumed one is taken as unknown to this many degrees "
                                      "until the pool holds the 5 searches it is first tested with: a step measured "
                                      "before then has its sigma widened by the length that pitch moves it (4-7% a "
                                      "degree for the region's depths; 0: sigma_fraction alone). With wheels such a "
                                      "step is not tied until the pitch is tested, then measured again on it")
    pitch_every: int = Field(1, ge=1, description="with pitch_window above 1, once pitch_window searches are pooled the "
                             "pitch is searched at every this many steps only (the search costs about four times the "
                             "length's alone; until the pool is full, at every step); the steps between are measured "
                             "on the pooled pitch. 3 was measured: 2.3x less cost, but the KITTI excerpts' fused runs "
                             "1.54x worse (docs/scale_suite.md)")
    sigma_fraction: float = Field(0.03, gt=0, description="sigma of a measured step's length, as a share of it")
    max_floor_landmarks: int | None = Field(
        50, ge=1, description="measure a step only while the window holds fewer than this many floor landmarks "
        "tied to the floor (the corners then tell the floor's scale already, and the region's pixels are the same "
        "floor's: a room's textured floor; a road's fused run ties none). null: every step")
    level_when_rocking: bool = Field(False, description="on a base rocking on its suspension (the window's keyframes "
                                     "tilting by more than ground.rocking_jitter_deg between keyframes), measure each "
                                     "step on the floor along the window's mean floor normal, seen from the step's "
                                     "first keyframe (its rocking applied) instead of the set-up's; false: always the "
                                     "set-up's (or the learnt mount's) normal. Off by default: the measured steps' spread halves on "
                                     "rocking runs, the scale suite's fused runs 1.002x (docs/scale_suite.md)")
    robust_k: float | None = Field(None, gt=0, description="threshold of the range factor's robust loss (the "
                                   "ground factors' kind) in sigmas; default: the 1-D chi-square quantile of "
                                   "backend.robust_confidence")


class GroundConfig(_Section):
    """Ground-plane scale cue: floor landmarks tied to the floor at the camera's known height."""

    enabled: bool = Field(True, description="tie floor landmarks to the ground plane (metric scale from the camera height)")
    camera_height_m: float | None = Field(None, gt=0, description="camera height above the floor; default: the z of "
                                          "T_base_cam (base origin on the floor)")
    sigma_height_fraction: float = Field(0.03, gt=0, description="sigma of a floor point's height, as a share of the "
                                         "camera height")
    sigma_common_fraction: float | None = Field(
        None, gt=0, description="sigma of the error all floor points tied at one keyframe share (the floor's "
        "height under the camera there: suspension, tyre compression, the local surface), as a share of the camera "
        "height, e.g. 0.015. A keyframe's n floor points then tell its height to sqrt(sigma_height^2 / n + this^2): "
        "the floor's information does not grow with the number of points. null (default: measured better on the "
        "scale suite's rendered floors, docs/scale_suite.md): independent points (n points: sigma / sqrt(n))")
    sigma_tilt_deg: float = Field(
        0.0, ge=0, lt=10, description="sigma of the floor's attitude against the base (a camera mount pitched "
        "against T_base_cam, a road's camber and changes of slope), in degrees: a floor point at range r then has a "
        "height error r tan(sigma) on top of sigma_height_fraction, so far points tell the scale less than near "
        "ones (a car's camera: about 1; docs/scale_suite.md). 0 (default): the floor is the base's xy plane exactly")
    robust: RobustKind = Field(RobustKind.HUBER, description="robust loss of the ground factor")
    robust_k: float | None = Field(None, gt=0, description="its threshold in sigmas; default: chi-square quantile, 1-D")
    min_depression_deg: float = Field(8.0, ge=0, lt=90, description="floor candidates lie at least this far below "
                                      "the horizon of the base frame, seen from the camera")
    max_range_heights: float = Field(15.0, gt=0, description="floor candidates lie within this many camera heights")
    max_tilt_deg: float = Field(6.0, gt=0, lt=45, description="the fitted floor plane may tilt this much from the "
                                "base frame's xy plane (more: a ramp or slope ahead, cue off for that keyframe)")
    height_tolerance: float = Field(0.25, gt=0, lt=1, description="the fitted plane must lie within this share of "
                                    "the camera height (else the cue is off for that keyframe)")
    inlier_height_fraction: float = Field(0.03, gt=0, description="RANSAC inlier distance: this share of the camera "
                                          "height ...")
    inlier_range_fraction: float = Field(0.005, ge=0, description="... plus this share of the point's range")
    min_points: int = Field(8, ge=3, description="floor points needed to accept a plane")
    max_landmarks: int = Field(120, ge=0, le=2000, description="floor landmarks in the window, on top of "
                               "backend.max_landmarks (they carry the scale)")
    seed: int = Field(0, description="seed of the plane RANSAC (runs are deterministic)")
    rocking_jitter_deg: float | None = Field(0.2, gt=0, description="the base counts as rocking on its suspension "
                                             "when the median change of its tilt between consecutive keyframes of "
                                             "the window exceeds this; floor points are then measured along the "
                                             "floor's normal (a level frame) instead of their keyframe's z axis. "
                                             "Measured: 0.009-0.014 on level rendered runs and the ramp, 0.6-2.5 "
                                             "with 0.5-2.5 deg of rocking. null: never")
    level_select_deg: float = Field(2.0, gt=0, le=20, description="level frame: the mean z axis of the window's "
                                    "keyframes within this angle of the fitted floor plane's normal")
    mount_calibration: MountCalibration = Field(
        MountCalibration.AUTO, description="measure floor heights along the floor's normal in the base frame learnt "
        "from the floor planes fitted so far (a camera mount pitched or rolled against T_base_cam: 1 deg made 5.5% of "
        "scale error on the rendered loop): auto: from the first keyframe where the learnt tilt exceeds 0.3 deg and "
        "three standard errors; on: always, tying no floor "
        "point before it is learnt; off: the base z axis (the normal is learnt and reported either way); "
        "true/false mean on/off")

    @field_validator("mount_calibration", mode="before")
    @classmethod
    def _mount_bool(cls, v):
        return {True: "on", False: "off"}.get(v, v) if isinstance(v, bool) else v

    mount_from_motion: bool = Field(
        False, description="learn the floor's tilt toward the base's +x (the mount's pitch) from the direction the "
        "base moves in, as vision alone measures it between keyframes (a ground robot moves along its floor), "
        "instead of from the fitted floor planes (the median of the last 10 steps; the roll stays the planes', and "
        "mount_calibration auto switches when either is significant). Needs no floor texture, and kerbs or "
        "pavements beside the path do not bias it")
    mount_min_fits: int = Field(10, ge=1, description="floor plane fits (with mount_from_motion: keyframe steps) "
                                "before the learnt normal is reported and used")
    mount_fits: int = Field(200, ge=1, description="the learnt normal is the median of this many latest fits")
    floor_state: bool = Field(
        False, description="each keyframe that ties floor points gets a floor frame F(k) of its own: a pose state "
        "tied to the keyframe's base pose with floor_tilt_sigma_deg in roll and pitch and floor_height_fraction in "
        "height (tight in the rest), and its floor points are tied to the floor of F(k), not of the base. The floor "
        "under a keyframe is then estimated geometry: its tilt against the base (a mount pitched against T_base_cam, "
        "a base rocking on its suspension) is taken from the points, and its height is known to no better than "
        "floor_height_fraction however many points it holds. Off: measured worse on the scale suite's rendered rooms "
        "and warehouses, whose floors are exact (docs/scale_suite.md, \"Floor frames\")")
    floor_tilt_sigma_deg: float = Field(1.0, gt=0, le=20, description="floor_state: sigma of the floor frame's roll "
                                        "and pitch against the base (mount error plus rocking)")
    floor_height_fraction: float = Field(0.015, gt=0, le=0.5, description="floor_state: sigma of the floor frame's "
                                         "height against the base, as a share of the camera height (suspension, "
                                         "tyres, the local surface)")
    height_sigma_fraction: float | None = Field(
        None, gt=0, le=0.5, description="how well camera_height_m is known, as a share of it (the suspension's "
        "load, the tyres, a road's crown: about 0.01-0.03 on a car). With it, the floor's depth below its "
        "configured height is a state shared by the keyframes (one per block that leaves the window together, a "
        "slow random walk, height_walk_per_sqrt_m), with this prior sigma, and each keyframe with floor points ties "
        "them to a floor frame dropped by that depth: the floor's information about the scale is then bounded by "
        "this sigma however many points it holds, and with wheels the fused scale weighs it against the wheel "
        "calibration's prior. null: the configured height is exact (each floor point carries its own scale "
        "information)")
    height_walk_per_sqrt_m: float = Field(0.001, gt=0, description="height_sigma_fraction: random walk of the "
                                          "floor's depth per sqrt(metre) driven, as a share of the camera height")

    @model_validator(mode="after")
    def _one_floor_frame(self) -> GroundConfig:
        if self.floor_state and self.height_sigma_fraction is not None:
            raise ValueError("backend.ground: floor_state and height_sigma_fraction each give the floor a frame of its "
                             "own; set one of them")
        return self
    untie_sigmas: float | None = Field(
        2.5, gt=0, description="after every update the window's tied floor landmarks are judged again: heights "
        "above the floor of the keyframe that tied each, in robust sigmas (1.4826 x MAD, at least 1% of the camera "
        "height) from their median. When at least twice as many lie beyond this many sigmas above as below (and 5 "
        "more: a surface just above the floor, kerbs, pavements, mats, that the plane fit took for it), those beyond "
        "it on either side lose their ground factors and keep their projections. Level-frame ground factors (a "
        "rocking base) are not judged. null: never")
    corridor_heights: float | None = Field(
        None, gt=0, description="after every update, the window's tied floor landmarks that the base has driven past "
        "farther than this many camera heights from its track (the window's keyframe base origins) lose their ground "
        "factors and keep their projections: the ground the wheels roll on is the floor at the camera's height by "
        "construction, the ground beside the track (kerbs, pavements, mats, platforms, a road's camber) only by "
        "assumption. A landmark still ahead of the newest keyframe or behind the oldest is not judged. 1.0 was "
        "measured: rooms and warehouses with platforms or mats beside the path fused 0.56-0.67x, but rooms without "
        "them 1.5x (docs/scale_suite.md, 'The ground beside the track'). null: never")
    reanchor_drifted_floor: bool = Field(
        True, description="without wheels (the floor the run's only scale source), a floor plane found at the same "
        "wrong height at two consecutive keyframes is the floor seen at a drifted scale (it was out of view while "
        "the monocular scale drifted) and is tied again, pulling the scale back; false: a plane off the camera "
        "height is never floor. Measured off on the scale suite's floor-only runs: 1.19x, a rocking street's "
        "0.39 -> 35 m (docs/scale_suite.md, \"The heuristics measured again\")")
    road_region: RoadRegionConfig = Field(RoadRegionConfig(), description="the floor measured by region: each "
                                          "keyframe step's length from the floor's pixels")

    @model_validator(mode="after")
    def _road_region_ahead(self):
        r = self.road_region
        for name in ("far_heights", "pitch_far_heights"):
            if getattr(r, name) <= r.near_heights:
                raise ValueError(f"road_region.{name} ({getattr(r, name)}) must be beyond near_heights "
                                 f"({r.near_heights})")
        return self


class WheelCalibrationConfig(_Section):
    """Online wheel calibration: distance scale, yaw bias per metre and yaw scale as slowly varying states."""

    enabled: bool = Field(True, description="estimate the wheels' scale, yaw bias and yaw scale in the window, from the first "
                          "keyframe whose floor landmarks fix the metric scale")
    initial_scale: float = Field(1.0, gt=0, description="the scale the calibration starts from (a robot's known "
                                 "calibration, e.g. a previous run's summary.json)")
    initial_yaw_bias_per_m: float = Field(0.0, description="the yaw bias (rad/m) it starts from")
    scale_prior_sigma: float = Field(0.03, gt=0, description="prior sigma of the scale (around initial_scale)")
    yaw_bias_prior_sigma: float = Field(0.02, gt=0, description="prior sigma of the yaw bias (rad/m, around "
                                        "initial_yaw_bias_per_m)")
    scale_walk_per_sqrt_m: float = Field(1e-3, gt=0, description="random walk of the scale per sqrt(metre)")
    yaw_bias_walk_per_sqrt_m: float = Field(2e-4, gt=0, description="random walk of the yaw bias per sqrt(metre)")
    initial_yaw_scale: float = Field(1.0, gt=0, description="the yaw scale it starts from: the wheels' heading change "
                                     "over the true one (a differential drive whose configured track width is 3% too "
                                     "narrow reports 1.03)")
    yaw_scale_prior_sigma: float = Field(0.05, gt=0, description="prior sigma of the yaw scale (around "
                                         "initial_yaw_scale)")
    yaw_scale_walk_per_sqrt_m: float = Field(1e-3, gt=0, description="random walk of the yaw scale per sqrt(metre)")


class CueCheckConfig(_Section):
    """Floor against wheels: a chi-square test of the scale each implies, per keyframe (backend/cue_check.py)."""

    enabled: bool = Field(True, description="test, at each keyframe with wheels and a floor plane (or a step the "
                          "floor's region measured on a tested pitch: the steps before its pitch pool holds 5 "
                          "searches count once they are measured again on it), whether the scale the floor implies "
                          "agrees with the wheels' (stats.csv cue_disagreement, cues_agree; the summary's share of "
                          "agreeing keyframes)")
    stretch_keyframes: int = Field(10, ge=1, le=500, description="the test compares distances and floor heights "
                                   "over this many latest keyframes")
    min_distance_m: float = Field(0.3, ge=0, description="... once the wheels drove at least this far over them")
    confidence: float = Field(0.99, gt=0.5, lt=1, description="the cues agree while the test's chi-square is within "
                              "its quantile at this confidence (1 degree of freedom)")
    gate: bool = Field(True, description="while they disagree, new floor points are not tied to the floor (the "
                       "wheels, whose scale error a tyre bounds, carry the scale); false: only report")


class ResetPriorConfig(_Section):
    """Prior that holds the last good pose when the window restarts after a smoother failure."""

    rotation_sigma_rad: float = Field(0.01, gt=0, description="rotation sigma of the reset prior")
    position_sigma_m: float = Field(0.02, gt=0, description="position sigma of the reset prior")


class BackendConfig(_Section):
    window_keyframes: int = Field(20, ge=3, le=500, description="keyframes in the fixed-lag window (at least; "
                                  "see marginalize_every)")
    marginalize_every: int = Field(6, ge=1, le=50, description="marginalise old keyframes in blocks of this many: "
                                   "the window then holds window_keyframes to window_keyframes + N - 1 keyframes, "
                                   "and only one update in N pays for a marginalisation (1: every update)")
    max_landmarks: int = Field(150, ge=10, le=5000, description="landmark budget of the window")
    budget_keyframes: Annotated[int, Field(ge=1, le=500)] | Literal["auto"] | None = Field(
        "auto", description="a landmark counts against the landmark budgets while one of the last N keyframes saw it "
        "(none: window_keyframes; 1: only landmarks the previous keyframe still saw, so landmarks whose tracks ended "
        "do not block new ones); auto (default): 1 without wheels, where vision carries the motion and more "
        "landmarks help, none with wheels, where more landmarks let Huber's outliers add up (docs/scale_suite.md)")
    min_landmarks_in_view: int = Field(20, ge=0, le=5000, description="new landmarks are admitted beyond the "
                                       "landmark budget while fewer than this many of the window's landmarks (off "
                                       "the floor) were seen by the previous keyframe: on a fast street, tracks end "
                                       "within a few keyframes and, with wheels (budget_keyframes auto), the budget "
                                       "fills with landmarks out of view, leaving keyframes with 0-6 landmarks in "
                                       "view for a window's length, where slipping wheels go unjudged (capped at "
                                       "max_landmarks; 0: the budget alone; 20, 40 and 80 measured, "
                                       "docs/scale_suite.md)")
    landmark_model: LandmarkModel = Field(LandmarkModel.EXPLICIT, description="landmarks off the floor: explicit (a "
                                          "point state and robust projection factors each) or smart (GTSAM smart "
                                          "projection factors, no point state; Gaussian pixel noise with the "
                                          "landmark dropped when an observation reprojects beyond "
                                          "outlier_residual_px); floor landmarks stay explicit. Measured less accurate (docs/performance.md)")
    min_landmark_observations: int = Field(3, ge=2, le=20, description="keyframes that must see a track before it is "
                                                                       "triangulated")
    two_view_guess: bool | Literal["auto"] = Field(
        "auto", description="a keyframe without wheels that PnP cannot place (its landmarks out of view) starts from "
        "the front end's two-view rotation and direction at the constant-velocity step's length (false: constant "
        "velocity); auto (default): true without wheels, false with wheels (their gaps keep constant velocity) "
        "(docs/scale_suite.md)")
    extra_iterations: int = Field(0, ge=0, le=10, description="extra iSAM2 updates per keyframe")
    optimizer: Literal["gauss_newton", "dogleg"] = Field("gauss_newton", description="iSAM2 step: gauss_newton or "
                                                                                     "dogleg")
    pixel_sigma: float = Field(1.0, gt=0, description="sigma of a projection (pixels)")
    robust: RobustKind = Field(RobustKind.HUBER, description="robust loss of the projection factors (huber, cauchy, "
                                                             "none)")
    huber_k: float | None = Field(None, gt=0, description="threshold of the pixel loss in sigmas; default: from the "
                                  "chi-square quantile (2-D) of robust_confidence")
    propagate_lens_noise: bool = Field(True, description="scale each observation's pixel sigma by the lens's "
                                       "undistortion stretch at that pixel (matters for wide-angle and fisheye lenses)")
    robust_confidence: float = Field(0.95, gt=0.5, lt=1, description="share of inlier residuals inside the robust "
                                     "threshold: thresholds come from the chi-square quantile of each factor's dimension")
    min_triangulation_angle_deg: float = Field(1.0, gt=0, lt=90, description="a track's rays must diverge this much "
                                                                             "before it is triangulated")
    max_reprojection_px: float = Field(3.0, gt=0, description="largest reprojection error of a newly triangulated "
                                                              "landmark")
    max_landmark_depth_m: float = Field(80.0, gt=0, description="landmarks further from the camera are not triangulated")
    outlier_residual_px: float = Field(6.0, gt=0, description="observations with a larger residual after an update are "
                                                              "removed")
    use_odometry: bool = Field(True, description="wheel-odometry between-factors (metric scale); false: monocular, up "
                                                 "to scale")
    relinearize_threshold: float = Field(0.05, gt=0, description="iSAM2 relinearisation threshold of the keyframe "
                                         "poses (rad and m) and the wheel calibration")
    landmark_relinearize_threshold_m: float | None = Field(
        0.3, gt=0, description="iSAM2 relinearisation threshold of the landmarks off the floor (m; floor landmarks "
        "keep relinearize_threshold; none: relinearize_threshold for all); most of an update's work is "
        "re-eliminating relinearised landmarks")
    relinearize_skip: int = Field(1, ge=1, le=100, description="iSAM2 relinearisation check every N updates")
    odometry: OdometryNoiseConfig = Field(OdometryNoiseConfig(), description="wheel-odometry factors: noise per metre, "
                                                                             "robust loss, gaps")
    planar_prior: PlanarPriorConfig = Field(PlanarPriorConfig(), description="roll/pitch (and height) prior for ground "
                                                                             "robots")
    ground: GroundConfig = Field(GroundConfig(), description="ground-plane scale cue: floor landmarks at the "
                                 "camera's known height make the scale metric, with or without wheels")
    wheel_calibration: WheelCalibrationConfig = Field(WheelCalibrationConfig(), description="online wheel "
                                                      "calibration (scale, yaw bias) as states in the window")
    reset_prior: ResetPriorConfig = Field(ResetPriorConfig(), description="prior on the last good pose when "
                                          "the window restarts after a failure")
    cue_check: CueCheckConfig = Field(CueCheckConfig(), description="floor against wheels: whether the scale each "
                                      "implies agrees, per keyframe; the floor gated off while they disagree")

    @field_validator("budget_keyframes", mode="before")
    @classmethod
    def _budget_keyframes_one_message(cls, v):
        """One message for a wrong value (the union's members would each report their own)."""
        if v is None or v == "auto" or (isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 500):
            return v
        raise ValueError(f"must be auto, null or a whole number of keyframes from 1 to 500, not {v!r}")

    def budget_lag(self, use_odometry: bool) -> int:
        """Keyframes back a landmark holds its place in the budgets (``budget_keyframes`` resolved)."""
        b = self.budget_keyframes
        if b == "auto":
            b = None if use_odometry else 1
        return self.window_keyframes if b is None else int(b)

    def uses_two_view_guess(self, use_odometry: bool) -> bool:
        """``two_view_guess`` resolved: auto is on without wheels."""
        return (not use_odometry) if self.two_view_guess == "auto" else bool(self.two_view_guess)


# Addresses ``viz.rerun: connect`` accepts: rerun[+http|+https]://HOST[:PORT]/proxy.
CONNECT_SCHEMES = ("rerun", "rerun+http", "rerun+https")


def connect_url_problem(url: str) -> str | None:
    """What is wrong with a Rerun viewer address (None: nothing)."""
    from urllib.parse import urlsplit

    hint = "expected rerun+http://HOST:PORT/proxy (e.g. rerun+http://127.0.0.1:9876/proxy)"
    try:
        parts = urlsplit(url)
        _ = parts.port
    except ValueError as err:
        return f"'{url}' is not a URL ({err}); {hint}"
    if parts.scheme not in CONNECT_SCHEMES:
        return f"'{url}': the scheme must be one of {', '.join(s + '://' for s in CONNECT_SCHEMES)}; {hint}"
    if not parts.hostname:
        return f"'{url}' has no host; {hint}"
    if parts.path != "/proxy":
        return f"'{url}': the path must be /proxy; {hint}"
    return None


class VizConfig(_Section):
    rerun: RerunMode = Field(RerunMode.SAVE, description="Rerun viewer: off, save (OUTPUT/recording.rrd), spawn (native"
                                                         " window), connect (to viz.connect_url), serve (web viewer)")
    connect_url: str = Field("rerun+http://127.0.0.1:9876/proxy", description="viewer address for rerun: connect")
    image_every: int = Field(1, ge=1, description="log the camera image and its overlays every N frames")
    jpeg_quality: int = Field(75, ge=1, le=100, description="JPEG quality of the logged camera image (1-100); "
                                                            "compressed images keep the recording cost low")

    @field_validator("connect_url")
    @classmethod
    def _connect_url(cls, v: str) -> str:
        problem = connect_url_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v

    @field_validator("rerun", mode="before")
    @classmethod
    def _yaml_off(cls, v):
        return yaml_off(v)
    track_tail: int = Field(10, ge=0, le=100, description="frames of track history drawn as tails on the image")


class CameraConfig(_Section):
    """Intrinsics for layouts that do not carry them (tum, folder)."""

    width: int = Field(gt=0, description="image width (pixels)")
    height: int = Field(gt=0, description="image height (pixels)")
    fx: float = Field(gt=0, description="focal length x (pixels)")
    fy: float = Field(gt=0, description="focal length y (pixels)")
    cx: float = Field(ge=0, description="principal point x (pixels)")
    cy: float = Field(ge=0, description="principal point y (pixels)")
    distortion_model: DistortionModel = Field(DistortionModel.NONE, description="lens distortion model")
    distortion: list[float] = Field([], description="distortion coefficients (radtan: k1 k2 p1 p2 [k3]; equidistant: k1"
                                                    " k2 k3 k4)")
    T_base_cam: list[float] | None = Field(None, description="camera mounting T_base_cam, 16 numbers row major; "
                                                             "default: at the base origin, looking forward")

    @field_validator("T_base_cam")
    @classmethod
    def _sixteen(cls, v):
        if v is not None and len(v) != 16:
            raise ValueError("T_base_cam needs 16 numbers (row major)")
        return v


class OdometrySynthesisConfig(_Section):
    """Wheel odometry made from ground truth, for datasets without wheels (labelled synthetic)."""

    enabled: bool = Field(False, description="synthesise wheel odometry from ground truth (datasets without wheels; "
                                             "labelled synthetic everywhere)")
    scale_error: float = Field(0.01, gt=-0.5, lt=0.5, description="distance scale error of the synthetic wheels")
    yaw_bias_per_m: float = Field(0.005, description="heading bias of the synthetic wheels (rad per metre)")
    noise: float = Field(0.002, ge=0, description="random-walk noise on distance (m) and heading (rad) per sqrt(metre)")
    seed: int = Field(0, description="random seed of that noise")


class OdometrySourceKind(str, enum.Enum):
    """Where a ROS bag's wheel odometry comes from."""

    AUTO = "auto"  # the one nav_msgs/Odometry topic, else odom_frame -> base_frame on /tf, else none
    MESSAGE = "message"  # nav_msgs/Odometry messages (odometry_topic, or the only such topic)
    TF = "tf"  # the odom_frame -> base_frame transform on /tf
    NONE = "none"  # no wheel odometry (monocular run)


class RosbagConfig(_Section):
    """Topics and frames of a ROS bag (``dataset: rosbag``); unset topics are auto-detected when unambiguous."""

    image_topic: str | None = Field(None, description="sensor_msgs/Image or CompressedImage topic (default: the only "
                                                      "image topic)")
    camera_info_topic: str | None = Field(None, description="sensor_msgs/CameraInfo topic (default: the only one, or "
                                                            "the one beside the image topic); the camera section wins")
    odometry_source: OdometrySourceKind = Field(OdometrySourceKind.AUTO, description="wheel odometry: auto, message "
                                                "(nav_msgs/Odometry), tf (odom_frame -> base_frame on /tf) or none")
    odometry_topic: str | None = Field(None, description="nav_msgs/Odometry topic (default: the only one not named "
                                                         "like ground truth)")
    base_frame: str | None = Field(None, description="base frame of T_base_cam (default: the odometry's child frame, "
                                                     "else base_link or base_footprint)")
    camera_frame: str | None = Field(None, description="camera (optical) frame (default: the frame_id of camera_info, "
                                                       "else of the images)")
    odom_frame: str = Field("odom", description="parent frame of the wheel-odometry transform on /tf")
    groundtruth_topic: str | None = Field(None, description="ground truth: PoseStamped or Odometry topic, the pose of "
                                                            "the base (default: the only one named like ground truth)")
    groundtruth_parent_frame: str | None = Field(None, description="or ground truth from /tf: the world frame ...")
    groundtruth_child_frame: str | None = Field(None, description="... and the base frame it moves")
    start_s: float = Field(0.0, ge=0, description="use images from this many seconds after the bag start (record "
                                                  "time)")
    end_s: float | None = Field(None, gt=0, description="... up to this many seconds after the bag start (none: the "
                                                        "end)")

    @model_validator(mode="after")
    def _check(self) -> RosbagConfig:
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError("rosbag.end_s must be greater than rosbag.start_s")
        if (self.groundtruth_parent_frame is None) != (self.groundtruth_child_frame is None):
            raise ValueError("rosbag.groundtruth_parent_frame and groundtruth_child_frame go together")
        if self.groundtruth_topic is not None and self.groundtruth_parent_frame is not None:
            raise ValueError("rosbag: give either groundtruth_topic or groundtruth_parent/child_frame, not both")
        if self.odometry_topic is not None and self.odometry_source in (OdometrySourceKind.TF, OdometrySourceKind.NONE):
            raise ValueError(f"rosbag.odometry_topic is set but odometry_source is '{self.odometry_source.value}'")
        return self


class InputChecksConfig(_Section):
    black_frame_mean: float = Field(4.0, ge=0, description="frames with a lower mean grey level are skipped as black")
    max_time_gap_factor: float = Field(3.0, gt=1, description="a timestamp gap over this many nominal frame intervals "
                                                              "is reported as dropped frames")


class Config(_Section):
    sequence: Path = Field(description="sequence folder (or file, for layouts that have one); relative to the config "
                                       "file")
    output: Path = Field(description="output folder, created if missing; relative to the config file")
    dataset: DatasetKind = Field(DatasetKind.NATIVE, description="input layout: native, or a loader for another layout "
                                                                 "(see docs/datasets.md)")
    fps: float = Field(20.0, gt=0, description="frame rate when the sequence has no timestamps (no times.txt, folder "
                                               "layout)")
    max_frames: int | None = Field(None, gt=1, description="stop after this many frames (none: all)")
    progress: bool = Field(True, description="progress bar (on a terminal only)")
    run_mode: RunMode = Field(RunMode.PIPELINED, description="pipelined: the back end runs in a worker process "
                              "beside decoding and the front end (both cores, same results); sequential: one process")
    opencv_threads: int = Field(0, ge=0, le=256, description="OpenCV's worker threads while a run goes (cv2."
                                "setNumThreads, put back after; the back-end process too); 0: OpenCV's own default "
                                "(one per core). 1 saves CPU where a core would otherwise idle: run_mode sequential, "
                                "the 640x480 loop: 0.83x the CPU at the same wall time; pipelined runs: no measurable "
                                "change (docs/performance.md)")
    camera: CameraConfig | None = Field(None, description="intrinsics and mounting for layouts that do not carry them "
                                                          "(tum, folder, video); for rosbag it wins over camera_info "
                                                          "and /tf_static")
    rosbag: RosbagConfig = Field(RosbagConfig(), description="topics and frames of a ROS bag (dataset: rosbag)")
    odometry_synthesis: OdometrySynthesisConfig = Field(OdometrySynthesisConfig(), description="synthetic wheel "
                                                                                               "odometry from ground "
                                                                                               "truth")
    frontend: FrontendConfig = Field(FrontendConfig(), description="front end: detection, tracking, undistortion, "
                                                                   "RANSAC")
    keyframes: KeyframeConfig = Field(KeyframeConfig(), description="keyframe selection")
    gates: GateConfig = Field(GateConfig(), description="quality gates a keyframe must pass for vision to be used")
    backend: BackendConfig = Field(BackendConfig(), description="fixed-lag smoother (GTSAM iSAM2)")
    viz: VizConfig = Field(VizConfig(), description="Rerun recording or live viewer")
    checks: InputChecksConfig = Field(InputChecksConfig(), description="screening of input frames")

    @model_validator(mode="before")
    @classmethod
    def _layout_defaults(cls, data):
        """Defaults that depend on the layout, applied while the config is built so that the validated (and
        resolved) config says what runs; an explicit setting always wins."""
        return apply_layout_defaults(data)

    @model_validator(mode="after")
    def _check(self) -> Config:
        if self.gates.min_parallax_px > self.keyframes.min_parallax_px:
            raise ValueError("gates.min_parallax_px must not exceed keyframes.min_parallax_px")
        return self

    def to_yaml_dict(self) -> dict:
        return self.model_dump(mode="json")


# Layouts recorded by hand-held cameras (tum) or drones (euroc): their base is not a ground
# robot's level, z-up base, so the priors that assume one are off unless the config sets them.
NOT_GROUND_ROBOT = (DatasetKind.TUM, DatasetKind.EUROC)


def apply_layout_defaults(data):
    """A config mapping with the layout's defaults filled in where the mapping leaves them unset (logged at INFO);
    anything else (not a mapping, an unknown dataset) is returned as it is, for validation to judge."""
    if not isinstance(data, dict):
        return data
    try:
        kind = DatasetKind(data.get("dataset", DatasetKind.NATIVE))
    except ValueError:
        return data
    backend = data.get("backend")
    pp = backend.get("planar_prior") if isinstance(backend, dict) else None
    if kind not in NOT_GROUND_ROBOT or (backend is not None and not isinstance(backend, dict)) or (
            pp is not None and (not isinstance(pp, dict) or "enabled" in pp)):
        return data
    log.info("dataset '%s' is hand-held or drone data (no level, z-up base): the planar roll/pitch prior is off; "
             "set backend.planar_prior.enabled=true to use it", kind.value)
    backend = dict(backend or {})
    backend["planar_prior"] = {**(pp or {}), "enabled": False}
    return {**data, "backend": backend}


def validation_problems(err: ValidationError) -> list[str]:
    """Every problem of a failed validation, one short phrase each (``'frontend.max_features': ...``)."""
    out = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e.get("loc", ()))
        msg = e.get("msg", "invalid value")
        if e.get("type") == "extra_forbidden":
            msg = "unknown key"
        elif e.get("type") == "missing":
            msg = "required key is missing"
        out.append(f"'{loc}': {msg}" if loc else msg)
    return out


def _format_validation_error(err: ValidationError) -> str:
    problems = validation_problems(err)
    head = "invalid config" if len(problems) == 1 else f"invalid config ({len(problems)} problems)"
    return f"{head}: " + "; ".join(problems)  # one line: WindowVOError escapes control characters


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """Apply ``dotted.key=value`` overrides; values are parsed as YAML scalars."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"invalid override '{item}': expected key=value, e.g. frontend.max_features=300")
        key, raw = item.split("=", 1)
        parts = [p for p in key.strip().split(".") if p]
        if not parts:
            raise ConfigError(f"invalid override '{item}': empty key")
        try:
            value = safe_load_yaml(raw) if raw.strip() else None
        except yaml.YAMLError:
            value = raw
        node = data
        for p in parts[:-1]:
            nxt = node.get(p)
            if nxt is None:
                nxt = {}
                node[p] = nxt
            if not isinstance(nxt, dict):
                raise ConfigError(f"invalid override '{item}': '{p}' is not a section")
            node = nxt
        node[parts[-1]] = value
    return data


def config_from_dict(data: dict, base_dir: Path | None = None) -> Config:
    """Validate a config mapping; relative paths are resolved against ``base_dir``."""
    if not isinstance(data, dict):
        raise ConfigError("invalid config: the top level must be a mapping of keys to values")
    try:
        cfg = Config.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err)) from None
    if base_dir is not None:
        base_dir = Path(base_dir)

        def fix(p: Path) -> Path:
            p = Path(p).expanduser()
            return p if p.is_absolute() else (base_dir / p).resolve()

        cfg.sequence = fix(cfg.sequence)
        cfg.output = fix(cfg.output)
        if cfg.frontend.mask is not None:
            cfg.frontend.mask = fix(cfg.frontend.mask)
        if cfg.frontend.mask_folder is not None:
            cfg.frontend.mask_folder = fix(cfg.frontend.mask_folder)
    return cfg


def read_yaml_mapping(path: Path | str, what: str, not_found: str | None = None) -> dict:
    """A YAML file whose top level is a mapping (empty file: ``{}``), or one clear ``ConfigError``; floats in
    any spelling (3.4e2, 1e-3) are read as floats."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(not_found or f"{what} not found: {path}")
    try:
        data = safe_load_yaml(path.read_text())
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read {what} {path}: {err}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{what} {path} is not valid YAML{where}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"invalid {what} {path}: the top level must be a mapping of keys to values")
    return data


def load_config(path: Path | str, overrides: list[str] | None = None) -> Config:
    """The run config of a YAML file (``sequence`` and ``output`` required; relative paths are relative to
    the file); ``overrides``: ``dotted.key=value`` as on the command line. For a robot, see
    :func:`load_robot_config`."""
    path = Path(path)
    data = read_yaml_mapping(path, "config", not_found=f"config file not found: {path}")
    data = apply_overrides(data, overrides or [])
    return config_from_dict(data, base_dir=path.parent.resolve())


# What a robot's config (the streaming API) has for the two keys only a file run needs.
ROBOT_PLACEHOLDERS = {"sequence": ".", "output": "."}


def robot_config_from_dict(data: dict, base_dir: Path | str | None = None) -> Config:
    """Validate a robot's config mapping: as :func:`config_from_dict`, but ``sequence`` and ``output`` (a
    file run's input and output folder) are not needed (when present they are kept, and unused)."""
    if not isinstance(data, dict):
        raise ConfigError("invalid config: the top level must be a mapping of keys to values")
    return config_from_dict({**ROBOT_PLACEHOLDERS, **data}, None if base_dir is None else Path(base_dir))


def load_robot_config(path: Path | str, overrides: list[str] | None = None) -> Config:
    """The config of a robot's YAML file for :class:`windowvo.Odometry` (the streaming API): every section
    of a run's config, without ``sequence`` or ``output`` (a robot has neither); relative paths (masks) are
    relative to the file. ``overrides``: ``dotted.key=value``."""
    path = Path(path)
    data = read_yaml_mapping(path, "config", not_found=f"config file not found: {path}")
    data = apply_overrides(data, overrides or [])
    return robot_config_from_dict(data, base_dir=path.parent.resolve())


def save_config(cfg: Config, path: Path | str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(cfg.to_yaml_dict(), sort_keys=False))
