"""``python -m windowvo.synth OUT [options]``: render a synthetic sequence in the native layout."""

from __future__ import annotations

import argparse
import sys
import time

from ..camera import DistortionModel
from .generate import SynthSpec, WheelErrorModel, generate_sequence
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
    p.add_argument("--fx", type=float, default=340.0)
    p.add_argument("--distortion-model", choices=[m.value for m in DistortionModel], default="none")
    p.add_argument("--distortion", default="", help="comma-separated coefficients")
    p.add_argument("--vibration-deg", type=float, default=0.0, help="roll/pitch vibration amplitude")
    p.add_argument("--ramp-height", type=float, default=0.0, help="ramp height in m (path=ramp uses 0.6 if 0)")
    p.add_argument("--obstacles", type=int, default=10)
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
    a = p.parse_args(argv)
    try:
        spec = SynthSpec(
            path=PathKind(a.path), duration_s=a.duration, fps=a.fps, speed=a.speed, seed=a.seed,
            width=a.width, height=a.height, fx=a.fx, distortion_model=DistortionModel(a.distortion_model),
            distortion=tuple(float(x) for x in a.distortion.split(",") if x.strip()),
            vibration_deg=a.vibration_deg, ramp_height_m=a.ramp_height, n_obstacles=a.obstacles, n_moving=a.moving,
            image_noise=a.image_noise, exposure_variation=a.exposure, exposure_jumps=a.exposure_jumps,
            wheel=WheelErrorModel(scale_error=a.odo_scale_error, yaw_bias_per_m=a.odo_yaw_bias,
                                  distance_noise=a.odo_noise, yaw_noise=a.odo_noise, slip_windows=_ranges(a.slip)),
            black_frames=_ints(a.black_frames), duplicate_frames=_ints(a.duplicate_frames),
            dropped_frames=_ints(a.dropped_frames), corrupt_frames=_ints(a.corrupt_frames),
            dark_frames=_pairs(a.dark_frames), blur_frames=_pairs(a.blur_frames),
            low_contrast_frames=_pairs(a.low_contrast_frames),
        )
        t0 = time.perf_counter()
        generate_sequence(a.out, spec, progress=True)
    except (ValueError, OSError) as err:
        print(f"windowvo.synth: error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {a.out} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
