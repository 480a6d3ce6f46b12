"""Synthetic sequences: rendered images, ground truth and imperfect wheel odometry.

``generate_sequence(out, spec)`` writes the native layout (images/, times.txt, camera.yaml,
odometry.csv, groundtruth.txt). Everything is deterministic for ``spec.seed``.
"""

from __future__ import annotations

import enum
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..camera import CameraModel, DistortionModel
from ..geometry import R_BASE_CAM_FORWARD, make_T, rot_x, rot_y
from ..io.odometry import WheelOdometry, write_odometry_csv
from ..io.odometry_synthesis import integrate_wheel_odometry
from ..io.sequence import write_camera_yaml
from ..io.trajectory import write_tum
from . import exact
from .paths import PathKind, PlanarPath, make_path
from .scene import MovingBox, Ramp, Renderer, Scene, make_room_scene
from .scenes import SceneKind, make_street_scene, make_warehouse_scene


class LensPreset(str, enum.Enum):
    """Ready-made lenses for 640x480 sequences."""

    PINHOLE = "pinhole"  # no distortion, 86 deg horizontal field of view
    RADTAN = "radtan"  # barrel distortion of a wide-angle robot camera: 104 deg horizontal, 116 deg diagonal
    FISHEYE = "fisheye"  # equidistant: 161 deg horizontal, 202 deg diagonal (the corners see behind the lens)


@dataclass(frozen=True)
class Lens:
    fx: float  # fy is the same
    distortion_model: DistortionModel
    distortion: tuple[float, ...]


LENSES: dict[LensPreset, Lens] = {
    LensPreset.PINHOLE: Lens(340.0, DistortionModel.NONE, ()),
    LensPreset.RADTAN: Lens(340.0, DistortionModel.RADTAN, (-0.28, 0.07, 0.0006, -0.0004)),
    LensPreset.FISHEYE: Lens(230.0, DistortionModel.EQUIDISTANT, (-0.01, 0.003, -0.0005, 0.00003)),
}


def lens_fields(preset: LensPreset) -> dict:
    """The :class:`SynthSpec` fields of a lens preset (``SynthSpec(**lens_fields(...), ...)``)."""
    lens = LENSES[LensPreset(preset)]
    return {"fx": lens.fx, "distortion_model": lens.distortion_model, "distortion": lens.distortion}


@dataclass
class WheelErrorModel:
    """How simulated wheel odometry departs from the truth."""

    scale_error: float = 0.01  # reported distance = (1 + scale_error) * true distance
    yaw_bias_per_m: float = 0.01  # rad of heading error added per metre driven
    distance_noise: float = 0.002  # m / sqrt(m) random walk on distance
    yaw_noise: float = 0.002  # rad / sqrt(m) random walk on heading
    slip_windows: list[tuple[float, float, float]] = field(default_factory=list)  # (t0, t1, extra factor)
    rate_hz: float = 100.0
    # A differential drive's track-width error scales every heading increment: reported yaw change =
    # (1 + yaw_scale_error) * true yaw change (0.03: the wheels report 3% too much turning).
    yaw_scale_error: float = 0.0

    def __post_init__(self) -> None:
        if not -0.5 < self.yaw_scale_error < 0.5:
            raise ValueError(f"the odometry's yaw_scale_error must lie in (-0.5, 0.5) (got {self.yaw_scale_error})")


# Paths the street can be laid along; the street scales them up (a loop of 80 m radius is a gentle curve).
STREET_PATHS = (PathKind.STRAIGHT, PathKind.LOOP, PathKind.STOP_AND_GO)
STREET_PATH_SIZE_M = 80.0

# What each scene changes in the SynthSpec defaults (the room: nothing); see SynthSpec.for_scene.
SCENE_DEFAULTS: dict[SceneKind, dict[str, Any]] = {
    SceneKind.ROOM: {},
    SceneKind.STREET: {"path": PathKind.STRAIGHT, "speed": 10.0, "fps": 10.0, "camera_height_m": 1.65,
                       "camera_pitch_deg": 1.0, "kerb_height_m": 0.13, "n_obstacles": 30},
    SceneKind.WAREHOUSE: {"speed": 1.0, "camera_height_m": 0.4, "camera_pitch_deg": 5.0, "n_obstacles": 12,
                          "n_moving": 1, "floor_contrast": 0.25},
}


def scene_defaults(kind: SceneKind) -> dict[str, Any]:
    """The SynthSpec fields a scene sets when the caller does not (a copy)."""
    return dict(SCENE_DEFAULTS[SceneKind(kind)])


@dataclass
class SynthSpec:
    path: PathKind = PathKind.LOOP
    duration_s: float = 20.0
    fps: float = 20.0
    speed: float = 0.8
    seed: int = 0
    width: int = 640
    height: int = 480
    fx: float = 340.0
    distortion_model: DistortionModel = DistortionModel.NONE
    distortion: tuple[float, ...] = ()
    camera_height_m: float = 0.45
    camera_pitch_deg: float = 8.0
    # The calibration written to camera.yaml claims the camera pitched down by this much more than it is (a
    # mount off its T_base_cam); the images and the ground truth keep the true mount.
    calib_pitch_error_deg: float = 0.0
    vibration_deg: float = 0.0  # roll/pitch vibration amplitude
    ramp_height_m: float = 0.0  # >0 puts a ramp in the path (use with path=ramp)
    floor_contrast: float = 1.0  # floor texture contrast (0: a featureless floor)
    n_obstacles: int = 10
    # Low platforms this high (m) on both sides of the path, textured like everything else: surfaces just
    # above the floor that a floor-plane fit can take for it (kerbs and pavements beside a road, mats, pallets).
    kerb_height_m: float = 0.0
    n_moving: int = 0
    image_noise: float = 0.0  # std of additive noise, grey levels
    exposure_variation: float = 0.0  # relative gain swing (0.3 = +-30 %)
    exposure_jumps: bool = False
    wheel: WheelErrorModel = field(default_factory=WheelErrorModel)
    black_frames: list[int] = field(default_factory=list)
    duplicate_frames: list[int] = field(default_factory=list)
    dropped_frames: list[int] = field(default_factory=list)
    corrupt_frames: list[int] = field(default_factory=list)
    dark_frames: list[tuple[int, int]] = field(default_factory=list)  # index ranges with gain 0.15
    blur_frames: list[tuple[int, int]] = field(default_factory=list)  # motion-blurred index ranges
    low_contrast_frames: list[tuple[int, int]] = field(default_factory=list)  # texture washed out (x0.08)
    # The first N frames show nothing below the horizon of the base frame (one flat grey): a run that starts
    # with no floor in view (a wall, a person in front of the camera).
    floor_hidden_frames: int = 0
    write_images: bool = True
    # What the camera drives through: the room, a street (n_obstacles parked cars, kerb_height_m the kerbs) or a
    # warehouse (n_obstacles pallets, n_moving people). SynthSpec.for_scene fills in each scene's defaults.
    scene: SceneKind = SceneKind.ROOM

    @classmethod
    def for_scene(cls, scene: SceneKind, **fields: Any) -> SynthSpec:
        """A spec of ``scene`` with its defaults (camera height, speed, fps, ...) where ``fields`` leave them."""
        return cls(scene=SceneKind(scene), **{**scene_defaults(scene), **fields})

    def __post_init__(self) -> None:
        self._check_scene()
        if not self.duration_s > 0 or not self.fps > 0:
            raise ValueError(f"duration and fps must be positive (got {self.duration_s} s at {self.fps} fps)")
        if self.floor_hidden_frames < 0:
            raise ValueError(f"floor_hidden_frames must be 0 or more (got {self.floor_hidden_frames})")
        if self.floor_contrast < 0:
            raise ValueError(f"floor_contrast must be 0 or more (got {self.floor_contrast})")
        if not 0.0 <= self.kerb_height_m < self.camera_height_m:
            raise ValueError(f"kerb_height_m must lie in [0, camera height {self.camera_height_m} m) "
                             f"(got {self.kerb_height_m})")

    def _check_scene(self) -> None:
        if not isinstance(self.scene, SceneKind):
            raise ValueError(f"scene must be one of {', '.join(k.value for k in SceneKind)} (got {self.scene!r})")
        if self.scene is SceneKind.STREET and self.path not in STREET_PATHS:
            raise ValueError(f"the street scene drives the paths {', '.join(k.value for k in STREET_PATHS)} "
                             f"(got {PathKind(self.path).value})")
        if self.scene is not SceneKind.ROOM and (self.path is PathKind.RAMP or self.ramp_height_m > 0):
            raise ValueError(f"ramps exist in the room scene only (scene {self.scene.value})")
        if not self.camera_height_m > 0:
            raise ValueError(f"camera_height_m must be positive (got {self.camera_height_m})")


@dataclass
class SyntheticWorld:
    spec: SynthSpec
    scene: Scene
    camera: CameraModel
    planar: PlanarPath

    def T_world_base(self, t: float) -> np.ndarray:
        return base_pose(self.planar, self.scene, t, self.spec.vibration_deg, self.spec.seed)


def camera_for(spec: SynthSpec) -> CameraModel:
    R_bc = exact.matmul(R_BASE_CAM_FORWARD, rot_x(-np.deg2rad(spec.camera_pitch_deg)))
    T_base_cam = make_T(R_bc, np.array([0.25, 0.0, spec.camera_height_m]))
    return CameraModel(
        spec.width,
        spec.height,
        spec.fx,
        spec.fx,
        spec.width / 2.0,
        spec.height / 2.0,
        spec.distortion_model,
        tuple(spec.distortion),
        T_base_cam,
    )


def base_pose(planar: PlanarPath, scene: Scene, t: float, vib_deg: float, seed: int) -> np.ndarray:
    x, y, yaw = (float(a) for a in planar.at(t))
    h = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    # A rigid robot with a 0.5 m wheelbase: its pitch follows the ground under the front and
    # rear axles, so crossing the kink at a ramp's foot tilts it gradually, as on a real robot.
    half_base = 0.25
    zf = scene.ground_height(x + half_base * h[0], y + half_base * h[1])
    zr = scene.ground_height(x - half_base * h[0], y - half_base * h[1])
    z = 0.5 * (zf + zr)
    xa = np.array([2 * half_base * h[0], 2 * half_base * h[1], zf - zr])
    xa /= exact.norm(xa)
    n_side = scene.ground_normal(x, y)
    ya = np.cross(n_side, xa)
    ya /= exact.norm(ya)
    n = np.cross(xa, ya)
    R = np.stack([xa, ya, n], axis=1)
    if vib_deg > 0:
        a = np.deg2rad(vib_deg)
        ph = (seed % 7) * 0.37
        roll = a * (0.7 * np.sin(2 * np.pi * 1.7 * t + ph) + 0.3 * np.sin(2 * np.pi * 4.3 * t))
        pitch = a * (0.6 * np.sin(2 * np.pi * 2.3 * t + 1.1 + ph) + 0.4 * np.sin(2 * np.pi * 5.1 * t))
        R = exact.matmul(exact.matmul(R, rot_y(pitch)), rot_x(roll))
        z += 0.004 * np.sin(2 * np.pi * 3.1 * t)
    return make_T(R, np.array([x, y, z]))


def _place_obstacles(rng, planar: PlanarPath, n: int, half: float, clearance: float = 1.3):
    pts = planar.points()[::20]
    out: list[tuple[float, float, float, float, float]] = []
    tries = 0
    while len(out) < n and tries < 5000:
        tries += 1
        ox, oy = rng.uniform(-half + 1.0, half - 1.0, 2)
        sx, sy = rng.uniform(0.4, 1.4, 2)
        sz = rng.uniform(0.6, 2.5)
        r = 0.5 * np.hypot(sx, sy)
        if np.min(np.hypot(pts[:, 0] - ox, pts[:, 1] - oy)) < clearance + r:
            continue
        out.append((ox, oy, sx, sy, sz))
    return out


# Kerbs: square platforms of KERB_SIZE_M every KERB_STEP_M along the path, KERB_SIDE_M either side of it,
# none closer than KERB_CLEARANCE_M to any point of the path (the robot never drives onto one).
KERB_STEP_M, KERB_SIDE_M, KERB_SIZE_M, KERB_CLEARANCE_M = 1.2, 0.75, 0.5, 0.45


def place_kerbs(planar: PlanarPath, height: float) -> list[tuple[float, float, float, float, float]]:
    """Low platforms ``(x, y, sx, sy, sz)`` on both sides of the path, ``height`` high."""
    pts = planar.points()
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    out: list[tuple[float, float, float, float, float]] = []
    for s in np.arange(0.5 * KERB_STEP_M, along[-1], KERB_STEP_M):
        i = min(int(np.searchsorted(along, s)), len(pts) - 2)
        tangent = pts[i + 1] - pts[i]
        if exact.norm(tangent) < 1e-9:
            continue
        side = np.array([-tangent[1], tangent[0]]) / exact.norm(tangent)
        for c in (pts[i] - KERB_SIDE_M * side, pts[i] + KERB_SIDE_M * side):
            if np.min(np.hypot(*(pts - c).T)) < KERB_CLEARANCE_M:
                continue  # where the path turns or crosses itself
            if any(np.hypot(c[0] - o[0], c[1] - o[1]) < KERB_SIZE_M for o in out):
                continue
            out.append((float(c[0]), float(c[1]), KERB_SIZE_M, KERB_SIZE_M, float(height)))
    return out


def _moving_boxes(spec: SynthSpec, rng: np.random.Generator, planar: PlanarPath) -> list[MovingBox]:
    """Boxes that cross the path back and forth, like people or forklifts."""
    moving = []
    for k in range(spec.n_moving):
        i = int(rng.integers(len(planar.t) // 5, 4 * len(planar.t) // 5))
        px, py, pyaw = planar.x[i], planar.y[i], planar.yaw[i]
        ahead = np.array([px, py]) + 2.5 * np.array([np.cos(pyaw), np.sin(pyaw)])
        side = np.array([-np.sin(pyaw), np.cos(pyaw)])
        moving.append(
            MovingBox(ahead - 2.5 * side, ahead + 2.5 * side, (0.5, 0.5, 1.7), float(rng.uniform(5, 8)), spec.seed + 100 + k)
        )
    return moving


def _room(spec: SynthSpec, rng: np.random.Generator, planar: PlanarPath) -> Scene:
    ramp = None
    half_x = 9.0
    if spec.path is PathKind.RAMP or spec.ramp_height_m > 0:
        h = spec.ramp_height_m if spec.ramp_height_m > 0 else 0.6
        ramp = Ramp(-2.0, 2.5, h)
        half_x = max(9.0, float(np.abs(planar.x).max()) + 3.0)
    half_x = max(half_x, float(np.abs(planar.x).max()) + 2.5)
    half_y = max(9.0, float(np.abs(planar.y).max()) + 2.5)
    obstacles = _place_obstacles(rng, planar, spec.n_obstacles, min(half_x, half_y))
    if spec.kerb_height_m > 0:
        obstacles += place_kerbs(planar, spec.kerb_height_m)
    moving = _moving_boxes(spec, rng, planar)
    return make_room_scene(spec.seed, half_x, half_y, 3.0, obstacles, ramp, moving, spec.floor_contrast)


def build_world(spec: SynthSpec) -> SyntheticWorld:
    rng = np.random.default_rng(spec.seed)
    if spec.scene is SceneKind.STREET:
        planar = make_path(spec.path, spec.duration_s, spec.speed, size=STREET_PATH_SIZE_M)
        scene = make_street_scene(spec.seed, planar, spec.kerb_height_m, spec.n_obstacles,
                                  _moving_boxes(spec, rng, planar))
    elif spec.scene is SceneKind.WAREHOUSE:
        planar = make_path(spec.path, spec.duration_s, spec.speed)
        kerbs = place_kerbs(planar, spec.kerb_height_m) if spec.kerb_height_m > 0 else []
        scene = make_warehouse_scene(spec.seed, planar, spec.n_obstacles, _moving_boxes(spec, rng, planar),
                                     spec.floor_contrast, kerbs)
    else:
        planar = make_path(spec.path, spec.duration_s, spec.speed)
        scene = _room(spec, rng, planar)
    return SyntheticWorld(spec, scene, camera_for(spec), planar)


def simulate_wheel_odometry(world: SyntheticWorld, err: WheelErrorModel, seed: int, label: str) -> WheelOdometry:
    """Integrate noisy planar increments of the true base motion (what wheel encoders see)."""
    ts = np.arange(0.0, world.planar.duration + 1e-9, 1.0 / err.rate_hz)
    T = np.stack([world.T_world_base(t) for t in ts])
    step = T[1:, :3, 3] - T[:-1, :3, 3]
    d = sum(T[:-1, j, :3] * step[:, j:j + 1] for j in range(3))  # the step in the previous base frame: R^T step
    ds = np.concatenate([[0.0], np.hypot(d[:, 0], d[:, 1]) * np.where(np.abs(d[:, 0]) > 1e-12, np.sign(d[:, 0]), 1.0)])
    # Heading change of the planar path only: roll/pitch vibration does not turn the wheels.
    dyaw = np.concatenate([[0.0], np.diff(world.planar.at(ts)[2])])
    comment = (
        f"{label} wheel odometry: scale_error={err.scale_error}, yaw_bias_per_m={err.yaw_bias_per_m}, "
        f"distance_noise={err.distance_noise}, yaw_noise={err.yaw_noise}, slip_windows={err.slip_windows}"
    )
    if err.yaw_scale_error != 0.0:  # (named only when set: odometry.csv of earlier specs stays as it was)
        dyaw = dyaw * (1.0 + err.yaw_scale_error)
        comment += f", yaw_scale_error={err.yaw_scale_error}"
    return integrate_wheel_odometry(ts, ds, dyaw, scale_error=err.scale_error, yaw_bias_per_m=err.yaw_bias_per_m,
                                    distance_noise=err.distance_noise, yaw_noise=err.yaw_noise,
                                    rng=np.random.default_rng(seed + 7919), slip_windows=err.slip_windows,
                                    comment=comment)


def frame_gain(spec: SynthSpec, i: int, rng: np.random.Generator) -> float:
    g = 1.0
    if spec.exposure_variation > 0:
        if spec.exposure_jumps:
            level = int(i // max(int(spec.fps * 2), 1))
            g *= 1.0 + spec.exposure_variation * (1 if level % 2 else -1) * 0.8
        else:
            g *= 1.0 + spec.exposure_variation * np.sin(2 * np.pi * i / (spec.fps * 6))
    for a, b in spec.dark_frames:
        if a <= i <= b:
            g *= 0.15
    return g


def below_horizon(cam: CameraModel) -> np.ndarray:
    """Pixels whose ray points below the horizon of the base frame, (h, w) bool."""
    rays = exact.matmul(cam.pixel_bearings(), cam.T_base_cam[:3, :3].T)
    with np.errstate(invalid="ignore"):
        return (rays[:, 2] < 0.0).reshape(cam.height, cam.width)


def _frame_image(renderer: Renderer, spec: SynthSpec, i: int, t: float, T_wb: np.ndarray, rng: np.random.Generator,
                 hidden: np.ndarray | None) -> np.ndarray:
    """Frame ``i`` as written: rendered, then blurred, washed out, noisy, hidden or black as the spec says."""
    cam = renderer.camera
    img, _ = renderer.render(exact.matmul(T_wb, cam.T_base_cam), t, gain=frame_gain(spec, i, rng))
    img = img * 255.0
    if any(a <= i <= b for a, b in spec.blur_frames):
        ksize = 15
        kern = np.zeros((ksize, ksize), np.float32)
        kern[ksize // 2, :] = 1.0 / ksize
        img = cv2.filter2D(img, -1, kern)
    if any(a <= i <= b for a, b in spec.low_contrast_frames):
        img = 128.0 + 0.08 * (img - float(img.mean()))
    if spec.image_noise > 0:
        img = img + rng.normal(0, spec.image_noise, img.shape).astype(np.float32)
    return _edited(spec, i, np.clip(img + 0.5, 0, 255).astype(np.uint8), hidden)


def _edited(spec: SynthSpec, i: int, img8: np.ndarray, hidden: np.ndarray | None) -> np.ndarray:
    """The frame faults that edit a rendered frame: the floor hidden (its pixels at the rest's mean), black."""
    if hidden is not None and i < spec.floor_hidden_frames:
        img8[hidden] = int(img8[~hidden].mean())
    if i in spec.black_frames:
        img8 = np.zeros_like(img8)
    return img8


def pixels_spec(spec: SynthSpec) -> SynthSpec:
    """The spec whose render holds ``spec``'s pixels before its frame faults: what only the estimator is told (the
    wheels' errors in odometry.csv, the claimed mount in camera.yaml) changes no pixel, and without image noise
    (whose random draws follow the rendered frames) the frame faults (hidden floor, black, duplicate, dropped,
    corrupt frames) are edits of the rendered frames. ``generate_sequence(out, spec, images_from=...)`` takes the
    images of that render."""
    base = replace(spec, wheel=WheelErrorModel(), calib_pitch_error_deg=0.0)
    if spec.image_noise == 0:
        base = replace(base, floor_hidden_frames=0, black_frames=[], duplicate_frames=[], dropped_frames=[],
                       corrupt_frames=[])
    return base


def _write_images(folder: Path, world: SyntheticWorld, frames: list[tuple[int, float, np.ndarray]],
                  progress: bool | Callable[[int, int], None], images_from: Path | None = None) -> None:
    """Render (or, with ``images_from``, read from the render of ``pixels_spec``) and write the kept frames
    ``(index, time, T_world_base)``, with the spec's faults; ``progress``: True prints a line every 50 frames, a
    callable gets (frames written, frames in all) after each."""
    spec = world.spec
    renderer = Renderer(world.scene, world.camera, seed=spec.seed) if images_from is None else None
    rng = np.random.default_rng(spec.seed + 1)
    hidden = below_horizon(world.camera) if spec.floor_hidden_frames > 0 else None
    last_img = None
    for k, (i, t, T_wb) in enumerate(frames):
        name = folder / f"{k:06d}.png"
        if i in spec.corrupt_frames:
            name.write_bytes(b"\x89PNG\r\n\x1a\n" + b"corrupt" * 10)
            continue
        if i in spec.duplicate_frames and last_img is not None:
            cv2.imwrite(str(name), last_img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            continue
        if renderer is not None:
            img8 = _frame_image(renderer, spec, i, t, T_wb, rng, hidden)
        else:
            assert images_from is not None
            img8 = _edited(spec, i, _read_frame(images_from / f"{i:06d}.png"), hidden)
        cv2.imwrite(str(name), img8, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        last_img = img8
        if callable(progress):
            progress(k + 1, len(frames))
        elif progress and k % 50 == 0:
            print(f"rendered {k}/{len(frames)}", flush=True)


def _read_frame(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"images_from: cannot read {path}")
    return img


def _write_tables(out: Path, world: SyntheticWorld, times: np.ndarray, gt_poses: list[np.ndarray]) -> None:
    """times.txt, camera.yaml, groundtruth.txt, odometry.csv and synth.json."""
    spec = world.spec
    (out / "times.txt").write_text("".join(f"{t:.6f}\n" for t in times))
    claimed = camera_for(replace(spec, camera_pitch_deg=spec.camera_pitch_deg + spec.calib_pitch_error_deg))
    write_camera_yaml(out / "camera.yaml", claimed if spec.calib_pitch_error_deg else world.camera)
    write_tum(out / "groundtruth.txt", times, np.stack(gt_poses), header="ground truth: T_world_base (TUM)")
    odo = simulate_wheel_odometry(world, spec.wheel, spec.seed, "synthetic")
    write_odometry_csv(out / "odometry.csv", odo)
    meta = asdict(spec)
    meta["path"] = spec.path.value
    meta["scene"] = spec.scene.value
    meta["distortion_model"] = DistortionModel(spec.distortion_model).value
    (out / "synth.json").write_text(json.dumps(meta, indent=1, default=str))


def generate_sequence(out: Path, spec: SynthSpec, progress: bool | Callable[[int, int], None] = False,
                      images_from: Path | None = None) -> SyntheticWorld:
    """Write the native sequence of ``spec`` into ``out`` (images/, times.txt, camera.yaml, odometry.csv,
    groundtruth.txt, synth.json). ``images_from``: the images/ folder of a sequence generated from
    ``pixels_spec(spec)``; its frames are taken instead of rendered again (the spec's frame faults applied to
    them), the same images bit for bit (a spec with image noise is always rendered: ValueError)."""
    out = Path(out)
    if images_from is not None and spec.image_noise > 0:
        raise ValueError("images_from: a spec with image noise is rendered (its noise follows the rendered frames)")
    world = build_world(spec)  # validates the camera before anything is written
    (out / "images").mkdir(parents=True, exist_ok=True)
    n = round(spec.duration_s * spec.fps) + 1
    times_all = np.arange(n) / spec.fps
    keep = [i for i in range(n) if i not in set(spec.dropped_frames)]
    frames = [(i, float(times_all[i]), world.T_world_base(times_all[i])) for i in keep]
    if spec.write_images:
        _write_images(out / "images", world, frames, progress, images_from)
    _write_tables(out, world, times_all[keep], [T for _, _, T in frames])
    return world


def shift_wheel_clock(seq: Path, out: Path, offset_s: float) -> Path:
    """A copy of the native sequence ``seq`` in ``out`` whose wheels' clock is ``offset_s`` ahead of the camera's
    (``t_wheels = t_camera + offset_s``): the stamps of odometry.csv alone are shifted, the images are linked (a
    driver-stamping fault, for measuring the wheel clock's estimate). Returns ``out``."""
    seq, out = Path(seq), Path(out)
    out.mkdir(parents=True, exist_ok=False)
    for f in seq.iterdir():
        if f.name == "images":
            (out / "images").symlink_to(f.resolve())
        elif f.is_file() and f.name != "odometry.csv":
            (out / f.name).write_bytes(f.read_bytes())
    rows = []
    for line in (seq / "odometry.csv").read_text().splitlines():
        if line[:1].isdigit():
            cells = line.split(",")
            cells[0] = f"{float(cells[0]) + offset_s:.6f}"
            line = ",".join(cells)
        rows.append(line)
    (out / "odometry.csv").write_text("\n".join(rows) + "\n")
    return out
