"""Typed, validated run configuration.

Each stage owns a parameter dataclass (pydantic model) that sits beside its algorithm in
spirit; they are gathered here so one YAML file configures a run. Loading rejects unknown
keys, wrong types and impossible values with one line that names the key.
"""

from __future__ import annotations

import enum
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .errors import ConfigError


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, use_enum_values=False)


class DatasetKind(str, enum.Enum):
    NATIVE = "native"
    KITTI = "kitti"
    TUM = "tum"
    EUROC = "euroc"
    FOLDER = "folder"


class TrackerKind(str, enum.Enum):
    KLT = "klt"
    ORB = "orb"


class RobustKind(str, enum.Enum):
    HUBER = "huber"
    CAUCHY = "cauchy"  # redescending: gross outliers (wheel slip) lose almost all weight
    NONE = "none"


class RerunMode(str, enum.Enum):
    OFF = "off"
    SAVE = "save"
    SPAWN = "spawn"
    CONNECT = "connect"
    SERVE = "serve"


class FrontendConfig(_Section):
    tracker: TrackerKind = TrackerKind.KLT
    max_features: int = Field(200, gt=8, le=5000)
    grid_cols: int = Field(8, ge=1, le=64)
    grid_rows: int = Field(6, ge=1, le=64)
    min_distance_px: float = Field(12.0, gt=0)
    quality_level: float = Field(0.01, gt=0, lt=1)
    klt_window_px: int = Field(9, ge=5, le=101)
    klt_levels: int = Field(3, ge=0, le=8)
    forward_backward_px: float = Field(0.5, gt=0)
    klt_max_residual: float = Field(8.0, gt=0)  # mean abs grey difference of the tracked patch
    ransac_threshold_px: float = Field(0.5, gt=0)
    ransac_confidence: float = Field(0.999, gt=0.5, lt=1)
    clahe: bool = False
    gain_normalization: bool = True
    gain_target: float = Field(110.0, gt=0, le=255, description="mean grey level that gain normalisation "
                               "scales every frame to")
    max_ray_angle_deg: float = Field(75.0, gt=0, lt=90, description="field-of-view bound: image regions and "
                                     "tracks whose ray is further off the optical axis are not used")
    mask: Path | None = None
    mask_folder: Path | None = None
    border_px: int = Field(8, ge=0)


class KeyframeConfig(_Section):
    min_parallax_px: float = Field(20.0, gt=0)
    min_tracked_ratio: float = Field(0.6, gt=0, lt=1)
    max_interval_s: float = Field(1.0, gt=0)
    standstill_parallax_px: float = Field(1.0, ge=0)
    standstill_distance_m: float = Field(0.01, ge=0)
    standstill_rotation_rad: float = Field(0.005, ge=0)


class GateConfig(_Section):
    min_parallax_px: float = Field(4.0, ge=0)
    min_inlier_ratio: float = Field(0.5, ge=0, le=1)
    min_cheirality_ratio: float = Field(0.8, ge=0, le=1)
    min_features: int = Field(25, ge=5)
    min_spread: float = Field(0.2, ge=0, le=1)


class OdometryNoiseConfig(_Section):
    xy_sigma_per_m: float = Field(0.02, gt=0)
    xy_sigma_min_m: float = Field(0.005, gt=0)
    yaw_sigma_per_m: float = Field(0.01, gt=0)
    yaw_sigma_min_rad: float = Field(0.002, gt=0)
    z_sigma_m: float = Field(0.05, gt=0)
    roll_pitch_sigma_rad: float = Field(0.05, gt=0)
    robust: RobustKind = RobustKind.CAUCHY
    robust_k: float = Field(1.0, gt=0)  # in sigmas
    max_gap_s: float = Field(0.5, gt=0)


class PlanarPriorConfig(_Section):
    enabled: bool = True
    sigma_rad: float = Field(0.1, gt=0)
    huber_k: float = Field(1.5, gt=0)
    height_prior: bool = False
    height_sigma_m: float = Field(0.5, gt=0)


class BackendConfig(_Section):
    window_keyframes: int = Field(20, ge=3, le=500)
    max_landmarks: int = Field(150, ge=10, le=5000)
    min_landmark_observations: int = Field(3, ge=2, le=20)  # keyframes that must see a track first
    extra_iterations: int = Field(0, ge=0, le=10)
    optimizer: Literal["gauss_newton", "dogleg"] = "gauss_newton"
    pixel_sigma: float = Field(1.0, gt=0)
    robust: RobustKind = RobustKind.HUBER
    huber_k: float = Field(1.345, gt=0)
    min_triangulation_angle_deg: float = Field(1.0, gt=0, lt=90)
    max_reprojection_px: float = Field(3.0, gt=0)
    max_landmark_depth_m: float = Field(80.0, gt=0)
    outlier_residual_px: float = Field(6.0, gt=0)
    use_odometry: bool = True
    relinearize_threshold: float = Field(0.05, gt=0)
    relinearize_skip: int = Field(1, ge=1, le=100)
    odometry: OdometryNoiseConfig = OdometryNoiseConfig()
    planar_prior: PlanarPriorConfig = PlanarPriorConfig()


class VizConfig(_Section):
    rerun: RerunMode = RerunMode.SAVE
    connect_url: str = "rerun+http://127.0.0.1:9876/proxy"
    image_every: int = Field(4, ge=1)  # camera image and its tracks every N frames (images dominate the cost)

    @field_validator("rerun", mode="before")
    @classmethod
    def _yaml_off(cls, v):
        # YAML 1.1 reads a bare `off` as false.
        return "off" if v is False else v
    track_tail: int = Field(10, ge=0, le=100)


class CameraConfig(_Section):
    """Intrinsics for layouts that do not carry them (tum, folder)."""

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float = Field(ge=0)
    cy: float = Field(ge=0)
    distortion_model: str = "none"
    distortion: list[float] = []
    T_base_cam: list[float] | None = None  # 16 numbers, row major; default: camera looking forward

    @field_validator("T_base_cam")
    @classmethod
    def _sixteen(cls, v):
        if v is not None and len(v) != 16:
            raise ValueError("T_base_cam needs 16 numbers (row major)")
        return v

    @field_validator("distortion_model")
    @classmethod
    def _model(cls, v):
        if v not in ("none", "radtan", "equidistant"):
            raise ValueError("must be none, radtan or equidistant")
        return v


class OdometrySynthesisConfig(_Section):
    """Wheel odometry made from ground truth, for datasets without wheels (labelled synthetic)."""

    enabled: bool = False
    scale_error: float = Field(0.01, gt=-0.5, lt=0.5)
    yaw_bias_per_m: float = 0.005
    noise: float = Field(0.002, ge=0)
    seed: int = 0


class InputChecksConfig(_Section):
    black_frame_mean: float = Field(4.0, ge=0)
    max_time_gap_factor: float = Field(3.0, gt=1)


class Config(_Section):
    sequence: Path
    output: Path
    dataset: DatasetKind = DatasetKind.NATIVE
    fps: float = Field(20.0, gt=0)
    max_frames: int | None = Field(None, gt=1)
    progress: bool = True
    camera: CameraConfig | None = None
    odometry_synthesis: OdometrySynthesisConfig = OdometrySynthesisConfig()
    frontend: FrontendConfig = FrontendConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    gates: GateConfig = GateConfig()
    backend: BackendConfig = BackendConfig()
    viz: VizConfig = VizConfig()
    checks: InputChecksConfig = InputChecksConfig()

    @model_validator(mode="after")
    def _check(self) -> Config:
        if self.gates.min_parallax_px > self.keyframes.min_parallax_px:
            raise ValueError("gates.min_parallax_px must not exceed keyframes.min_parallax_px")
        return self

    def to_yaml_dict(self) -> dict:
        return self.model_dump(mode="json")


def _format_validation_error(err: ValidationError) -> str:
    first = err.errors()[0]
    loc = ".".join(str(p) for p in first.get("loc", ()))
    msg = first.get("msg", "invalid value")
    if first.get("type") == "extra_forbidden":
        msg = "unknown key"
    elif first.get("type") == "missing":
        msg = "required key is missing"
    where = f"'{loc}'" if loc else "config"
    more = f" (and {len(err.errors()) - 1} more problem(s))" if len(err.errors()) > 1 else ""
    return f"invalid config: {where}: {msg}{more}"


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
            value = yaml.safe_load(raw) if raw.strip() else None
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

        def fix(p: Path | None) -> Path | None:
            if p is None:
                return None
            p = Path(p).expanduser()
            return p if p.is_absolute() else (base_dir / p).resolve()

        cfg.sequence = fix(cfg.sequence)
        cfg.output = fix(cfg.output)
        cfg.frontend.mask = fix(cfg.frontend.mask)
        cfg.frontend.mask_folder = fix(cfg.frontend.mask_folder)
    return cfg


def load_config(path: Path | str, overrides: list[str] | None = None) -> Config:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        text = path.read_text()
        data = yaml.safe_load(text)
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read config {path}: {err}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"config {path} is not valid YAML{where}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"invalid config {path}: the top level must be a mapping of keys to values")
    data = apply_overrides(data, overrides or [])
    return config_from_dict(data, base_dir=path.parent.resolve())


def save_config(cfg: Config, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(cfg.to_yaml_dict(), sort_keys=False))
