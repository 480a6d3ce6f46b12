"""``python -m windowvo.synth OUT [options]``: render a synthetic sequence in the native layout
(a room, a street or a warehouse), optionally also as a ROS bag beside it."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from ..camera import DistortionModel
from ..errors import WindowVOError, cli_error
from .bagwriter import BagFormat, bag_path_beside, bag_spec_for, check_bag_target, write_bag
from .generate import (
    LENSES,
    SCENE_DEFAULTS,
    LensPreset,
    SynthSpec,
    WheelErrorModel,
    generate_sequence,
    lens_fields,
)
from .paths import PathKind
from .scenes import SceneKind

# Options whose default depends on the scene: command-line name -> SynthSpec field (unset: the scene's default).
SCENE_OPTIONS = {"path": "path", "fps": "fps", "speed": "speed", "camera_height": "camera_height_m",
                 "camera_pitch": "camera_pitch_deg", "obstacles": "n_obstacles", "kerb_height": "kerb_height_m",
                 "floor_contrast": "floor_contrast", "moving": "n_moving"}


def _ranges(text: str) -> list[tuple[float, float, float]]:
    out = []
    for part in filter(None, text.split(";")):
        a, b, f = (float(x) for x in part.split(","))
        out.append((a, b, f))
    return out


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def _pairs(text: str) -> list[tuple[int, int]]:
    out = []
    for part in filter(None, text.split(";")):
        a, b = (int(x) for x in part.split(","))
        out.append((a, b))
    return out


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line and exit 2, like every other bad value
        sys.exit(cli_error(message))


def _scene_default(field: str) -> str:
    """'default: 20 (street: 10)' for the help of a scene-dependent option."""
    base = SynthSpec.__dataclass_fields__[field].default
    show = lambda v: v.value if isinstance(v, PathKind) else v  # noqa: E731
    others = [f"{k.value}: {show(d[field])}" for k, d in SCENE_DEFAULTS.items() if field in d]
    return f"default: {show(base)}" + (f" ({', '.join(others)})" if others else "")


def _add_scene_options(p: argparse.ArgumentParser) -> None:
    S = argparse.SUPPRESS
    p.add_argument("--scene", choices=[k.value for k in SceneKind], default="room",
                   help="room (walls and boxes), street (road, lane markings, kerbs, parked cars, facades; a 1.65 m "
                        "camera at 10 m/s) or warehouse (shiny floor, racks, pallets, a person walking; camera 0.4 m)")
    p.add_argument("--path", choices=[k.value for k in PathKind], default=S,
                   help=_scene_default("path") + "; the street takes straight, loop (a gentle 80 m radius curve) "
                        "or stop_and_go")
    p.add_argument("--fps", type=float, default=S, help=_scene_default("fps"))
    p.add_argument("--speed", type=float, default=S, help="m/s, " + _scene_default("speed"))
    p.add_argument("--camera-height", type=float, default=S, help="m above the floor, " + _scene_default("camera_height_m"))
    p.add_argument("--camera-pitch", type=float, default=S, help="deg down, " + _scene_default("camera_pitch_deg"))
    p.add_argument("--obstacles", type=int, default=S,
                   help="boxes (room), parked cars (street), pallets (warehouse); " + _scene_default("n_obstacles"))
    p.add_argument("--kerb-height", type=float, default=S,
                   help="room, warehouse: low platforms this high (m) on both sides of the path (kerbs, mats), 0: "
                        "none; street: the kerb height; " + _scene_default("kerb_height_m"))
    p.add_argument("--floor-contrast", type=float, default=S,
                   help="floor texture contrast (0: featureless), " + _scene_default("floor_contrast"))
    p.add_argument("--moving", type=int, default=S,
                   help="moving obstacles (people) crossing the path, " + _scene_default("n_moving"))


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m windowvo.synth", description=__doc__.replace("``", ""),
                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("out", help="output folder (native sequence layout)")
    _add_scene_options(p)
    p.add_argument("--duration", type=float, default=20.0, help="seconds")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=640, help="image width (KITTI-like: --width 1226 --height 370 --fx 707)")
    p.add_argument("--height", type=int, default=480, help="image height")
    p.add_argument("--lens", choices=[k.value for k in LensPreset], default="pinhole",
                   help="lens preset: pinhole (86 deg), radtan (104 deg, barrel), fisheye (equidistant, 161 deg "
                        "horizontal, 202 deg diagonal); --fx, --distortion-model, --distortion override its values")
    p.add_argument("--fx", type=float, default=None, help="focal length in pixels (fy = fx); default: the lens's")
    p.add_argument("--distortion-model", choices=[m.value for m in DistortionModel], default=None,
                   help="default: the lens's")
    p.add_argument("--distortion", default=None,
                   help="comma-separated coefficients: radtan k1,k2,p1,p2[,k3]; equidistant k1,k2,k3,k4")
    p.add_argument("--vibration-deg", type=float, default=0.0, help="roll/pitch vibration amplitude")
    p.add_argument("--calib-pitch-error-deg", type=float, default=0.0,
                   help="camera.yaml claims the camera pitched down this much more than it is (a mount off its "
                        "calibration)")
    p.add_argument("--ramp-height", type=float, default=0.0, help="ramp height in m (path=ramp uses 0.6 if 0)")
    _add_fault_options(p)
    p.add_argument("--bag", choices=[f.value for f in BagFormat], default=None,
                   help="also write the sequence as a bag beside OUT: OUT.bag (ros1), OUT_ros2/ (ros2, sqlite3) or "
                        "OUT_mcap/ (ros2, mcap); windowvo reads it with dataset: rosbag")
    return p


def _add_fault_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image-noise", type=float, default=0.0, help="grey-level std")
    p.add_argument("--exposure", type=float, default=0.0, help="relative gain swing, e.g. 0.3")
    p.add_argument("--exposure-jumps", action="store_true", help="step changes instead of a smooth swing")
    p.add_argument("--odo-scale-error", type=float, default=0.01)
    p.add_argument("--odo-yaw-bias", type=float, default=0.01, help="rad per m")
    p.add_argument("--odo-yaw-scale-error", type=float, default=0.0,
                   help="track-width error: the wheels report (1 + this) x every yaw change (0.03: 3%% too much)")
    p.add_argument("--odo-noise", type=float, default=0.002, help="m/sqrt(m) and rad/sqrt(m)")
    p.add_argument("--slip", default="", help="slip windows 't0,t1,extra;...' (extra 0.3 = wheels read 30%% more)")
    p.add_argument("--black-frames", default="", help="frame indices, comma-separated")
    p.add_argument("--duplicate-frames", default="")
    p.add_argument("--dropped-frames", default="")
    p.add_argument("--corrupt-frames", default="")
    p.add_argument("--dark-frames", default="", help="index ranges 'a,b;c,d'")
    p.add_argument("--blur-frames", default="", help="index ranges 'a,b;c,d'")
    p.add_argument("--low-contrast-frames", default="", help="index ranges 'a,b;c,d' (texture washed out)")
    p.add_argument("--floor-hidden-frames", type=int, default=0,
                   help="the first N frames show nothing below the horizon (a start with no floor in view)")


def _lens(a: argparse.Namespace) -> dict[str, Any]:
    lens = lens_fields(LensPreset(a.lens))
    if a.fx is not None:
        lens["fx"] = a.fx
    if a.distortion_model is not None:
        lens["distortion_model"] = DistortionModel(a.distortion_model)
        if a.distortion is None and lens["distortion_model"] is not LENSES[LensPreset(a.lens)].distortion_model:
            lens["distortion"] = ()
    if a.distortion is not None:
        lens["distortion"] = tuple(float(x) for x in a.distortion.split(",") if x.strip())
    return lens


def spec_from_args(a: argparse.Namespace) -> SynthSpec:
    """The SynthSpec of parsed command-line arguments (scene defaults where an option is not given)."""
    given = {field: getattr(a, opt) for opt, field in SCENE_OPTIONS.items() if hasattr(a, opt)}
    if "path" in given:
        given["path"] = PathKind(given["path"])
    return SynthSpec.for_scene(
        SceneKind(a.scene), duration_s=a.duration, seed=a.seed, width=a.width, height=a.height, **_lens(a),
        vibration_deg=a.vibration_deg, calib_pitch_error_deg=a.calib_pitch_error_deg, ramp_height_m=a.ramp_height,
        image_noise=a.image_noise, exposure_variation=a.exposure, exposure_jumps=a.exposure_jumps,
        wheel=WheelErrorModel(scale_error=a.odo_scale_error, yaw_bias_per_m=a.odo_yaw_bias,
                              distance_noise=a.odo_noise, yaw_noise=a.odo_noise, slip_windows=_ranges(a.slip),
                              yaw_scale_error=a.odo_yaw_scale_error),
        black_frames=_ints(a.black_frames), duplicate_frames=_ints(a.duplicate_frames),
        dropped_frames=_ints(a.dropped_frames), corrupt_frames=_ints(a.corrupt_frames),
        dark_frames=_pairs(a.dark_frames), blur_frames=_pairs(a.blur_frames),
        low_contrast_frames=_pairs(a.low_contrast_frames), floor_hidden_frames=a.floor_hidden_frames,
        **given,
    )


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    try:
        spec = spec_from_args(a)
        bag = bag_path_beside(Path(a.out), BagFormat(a.bag)) if a.bag else None
        if bag is not None:
            check_bag_target(bag)  # before the rendering, not after it
        t0 = time.perf_counter()
        generate_sequence(a.out, spec, progress=True)
        if bag is not None:
            write_bag(Path(a.out), bag, bag_spec_for(BagFormat(a.bag)))
    except (WindowVOError, ValueError, OSError) as err:
        return cli_error(err)
    also = f" and the {a.bag} bag {bag}" if bag is not None else ""
    print(f"wrote {a.out}{also} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
