"""What a back end's run says about its scale, typed: ``ScaleReport`` (summary.json, ``RunResult``).

Built from a live back end in this process (:func:`scale_report`) or sent back by the pipelined mode's
worker process; the same fields either way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ..types import ScaleSource, WheelCalibration

if TYPE_CHECKING:  # pragma: no cover
    from ..camera import CameraModel
    from ..config import BackendConfig
    from .smoother import SlidingWindowBackend

# Smallest camera height (m) for which the ground cue makes sense.
MIN_CAMERA_HEIGHT_M = 0.05


@dataclass(frozen=True)
class ScalePlan:
    """The metric cues a back end will use, known from the camera and the config before any keyframe."""

    use_odometry: bool
    use_ground: bool  # the floor at the camera's known height
    camera_height_m: float  # above the floor
    calibration_wanted: bool  # the wheels are calibrated online once the floor is in view


def plan_scale(camera: CameraModel, cfg: BackendConfig, use_odometry: bool) -> ScalePlan:
    """The cues of a back end on this camera and config (the same rule ``SlidingWindowBackend`` applies)."""
    g = cfg.ground
    cam_z = float(camera.T_base_cam[2, 3])
    height = float(g.camera_height_m) if g.camera_height_m is not None else cam_z
    return ScalePlan(use_odometry, g.enabled and height >= MIN_CAMERA_HEIGHT_M, height,
                     use_odometry and cfg.wheel_calibration.enabled)


@dataclass(frozen=True)
class ScaleReport:
    """Whether a run is metric, what fixed its scale, and what the floor and the wheels did to it."""

    metric: bool = False  # the scale is metric (wheels, or the ground plane at the camera height)
    scale_sources: list[str] = field(default_factory=list)  # ScaleSource values
    wheel_calibration: WheelCalibration | None = None  # final online estimate (with wheels)
    # A monocular run that saw the floor only later: metric from this frame on (the trajectory before it
    # rescaled, the causal poses before it up to scale).
    metric_from_frame: int | None = None
    # A monocular run whose scale drifted while the floor was out of view: keyframes where the floor was taken
    # back at the drifted height (its ground factors then pull the scale back).
    floor_scale_reanchors: int = 0
    # Ground factors removed from floor landmarks that later turned out to lie off the floor (a kerb beside it).
    floor_untied: int = 0
    # Of them, beside the track the base drove (ground.corridor_heights).
    floor_beside_track: int = 0
    # ground.height_sigma_fraction: the floor's estimated depth below its configured height (m; None: not estimated)
    floor_depth_m: float | None = None
    n_resets: int = 0  # back-end window resets

    @classmethod
    def lost(cls, metric: bool) -> ScaleReport:
        """A run aborted at once in pipelined mode: what the worker knew about the scale is lost."""
        return cls(metric=metric)


def scale_sources(be: SlidingWindowBackend) -> list[ScaleSource]:
    """What fixes the metric scale of a back end's run: the wheels, and the floor once it has ground factors (or the
    floor region's range factors) in the smoother. A monocular run that is metric owes it to the floor alone (its
    first baseline, or its late metric start), whether or not a ground factor followed (a run ending right after the
    floor came into view has none)."""
    out = []
    if be.use_odometry:
        out.append(ScaleSource.WHEELS_CALIBRATED if be.calibrate else ScaleSource.WHEELS)
    floor_made_metric = be.metric and not be.use_odometry
    if be.use_ground and (be.n_ground_factors > 0 or be.road.n_factors > 0 or floor_made_metric):
        out.append(ScaleSource.GROUND_PLANE)
    return out


def scale_report(be: SlidingWindowBackend) -> ScaleReport:
    """The scale report of a back end in this process."""
    return ScaleReport(
        metric=bool(be.metric),
        scale_sources=[s.value for s in be.scale_sources()],
        wheel_calibration=be.calibration_with_sigma() if be.calibrate and be.k >= 0 else None,
        metric_from_frame=None if be.metric_from_keyframe is None else be.kf_frame[be.metric_from_keyframe],
        floor_scale_reanchors=be.n_scale_reanchors,
        floor_untied=be.n_floor_untied,
        floor_beside_track=be.floor.n_floor_beside_track,
        floor_depth_m=be.floor.depth.depth_m if be.floor.depth.estimated else None,
        n_resets=be.n_resets,
    )
