"""``python -m windowvo.synth OUT [options]``: render a synthetic sequence in the native layout."""

from __future__ import annotations

import argparse
import sys
import time

from ..camera import DistortionModel
from ..errors import WindowVOError, cli_error
from .generate import LENSES, LensPreset, SynthSpec, WheelErrorModel, generate_sequence, lens_fields
from .paths import PathKind


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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.synth", description=__doc__.strip("`"),
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("out", help="output folder (native sequence layout)")
    p.add_argument("--path", choices=[k.value for k in PathKind], default="loop")
    p.add_argument("--duration", type=float, default=20.0, help="seconds")
    p.add_argument("--fps", type=float, default=20.0)
    p.add_argument("--speed", type=float, default=0.8, help="m/s")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
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
    p.add_argument("--obstacles", type=int, default=10)
    p.add_argument("--kerb-height", type=float, default=0.0,
                   help="low platforms this high (m) on both sides of the path (kerbs, mats); 0: none")
    p.add_argument("--floor-contrast", type=float, default=1.0, help="floor texture contrast (0: featureless)")
    p.add_argument("--moving", type=int, default=0, help="moving obstacles crossing the path")
    p.add_argument("--image-noise", type=float, default=0.0, help="grey-level std")
    p.add_argument("--exposure", type=float, default=0.0, help="relative gain swing, e.g. 0.3")
    p.add_argument("--exposure-jumps", action="store_true", help="step changes instead of a smooth swing")
    p.add_argument("--odo-scale-error", type=float, default=0.01)
    p.add_argument("--odo-yaw-bias", type=float, default=0.01, help="rad per m")
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
    a = p.parse_args(argv)
    try:
        lens = lens_fields(LensPreset(a.lens))
        if a.fx is not None:
            lens["fx"] = a.fx
        if a.distortion_model is not None:
            lens["distortion_model"] = DistortionModel(a.distortion_model)
            if a.distortion is None and lens["distortion_model"] is not LENSES[LensPreset(a.lens)].distortion_model:
                lens["distortion"] = ()
        if a.distortion is not None:
            lens["distortion"] = tuple(float(x) for x in a.distortion.split(",") if x.strip())
        spec = SynthSpec(
            path=PathKind(a.path), duration_s=a.duration, fps=a.fps, speed=a.speed, seed=a.seed,
            width=a.width, height=a.height, **lens,
            vibration_deg=a.vibration_deg, calib_pitch_error_deg=a.calib_pitch_error_deg, ramp_height_m=a.ramp_height, n_obstacles=a.obstacles, n_moving=a.moving,
            kerb_height_m=a.kerb_height, floor_contrast=a.floor_contrast,
            image_noise=a.image_noise, exposure_variation=a.exposure, exposure_jumps=a.exposure_jumps,
            wheel=WheelErrorModel(scale_error=a.odo_scale_error, yaw_bias_per_m=a.odo_yaw_bias,
                                  distance_noise=a.odo_noise, yaw_noise=a.odo_noise, slip_windows=_ranges(a.slip)),
            black_frames=_ints(a.black_frames), duplicate_frames=_ints(a.duplicate_frames),
            dropped_frames=_ints(a.dropped_frames), corrupt_frames=_ints(a.corrupt_frames),
            dark_frames=_pairs(a.dark_frames), blur_frames=_pairs(a.blur_frames),
            low_contrast_frames=_pairs(a.low_contrast_frames), floor_hidden_frames=a.floor_hidden_frames,
        )
        t0 = time.perf_counter()
        generate_sequence(a.out, spec, progress=True)
    except (WindowVOError, ValueError, OSError) as err:
        return cli_error(err)
    print(f"wrote {a.out} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
