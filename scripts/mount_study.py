"""Study (issue #26 items 5 and 7): the mount switch on sequences whose camera.yaml claims a pitch the camera does not have.

    python scripts/mount_study.py --work DIR [--jobs 2] [--base K=V ...] [--set K=V ...]

Renders 10 sequences into DIR (rooms and warehouses 12 s, streets 8 s, seeds 401-410; wheels -2% to +3%) whose
camera is pitched against its ``T_base_cam`` by +1, +0.5, -0.5 or -1 deg (``calib_pitch_error_deg``: positive, the
camera looks further down than camera.yaml says), two of them exact, and runs each fused twice: with the ``--base``
overrides and with the ``--set`` ones (default: both the defaults). Prints per sequence the ATE SE(3), the keyframes
at which the learnt floor normal was in use (``floor_normal_learnt``: the switch of ``ground.mount_calibration:
auto``), the learnt tilt toward +x at the end (the mount's pitch as the plane fits see it) and the wheel calibration's
final scale, then the ratios' geometric mean and worst case. docs/scale_suite.md, "The mount switch's wheel release,
the plane fits' pitch, and the region's pixel selection again (stop 58)", quotes it.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

# (scene, path, seed, the camera's pitch against camera.yaml in deg, the wheels' scale error)
CASES = [("room", "loop", 401, 1.0, 0.02), ("room", "figure_eight", 402, -0.5, -0.01), ("room", "loop", 403, 0.5, 0.01),
         ("warehouse", "loop", 404, 1.0, -0.02), ("warehouse", "figure_eight", 405, -1.0, 0.02),
         ("warehouse", "straight", 406, 0.5, 0.03), ("street", "straight", 407, 1.0, 0.02),
         ("street", "loop", 408, -1.0, -0.02), ("room", "loop", 409, 0.0, 0.02), ("warehouse", "loop", 410, 0.0, -0.02)]


def run_case(args: tuple[Path, tuple, tuple[str, ...], tuple[str, ...]]) -> tuple[str, list[tuple[float, int, float,
                                                                                                    float]]]:
    """(ATE SE(3), keyframes with the learnt normal in use, final learnt x tilt, final wheel scale) per setting."""
    work, (scene, path, seed, pitch, scale), base, new = args
    logging.disable(logging.WARNING)
    from windowvo.config import config_from_dict
    from windowvo.runtime.job import run_job
    from windowvo.tools import scale_suite as ss

    spec: dict = {"path": path, "seed": seed, "duration_s": 8.0 if scene == "street" else 12.0,
                  "calib_pitch_error_deg": pitch, "wheel": {"scale_error": scale, "yaw_bias_per_m": 0.004}}
    if scene == "street":
        spec.update(ss.STREET_IMAGE)
    case = ss.ScaleCase(f"{scene}_{path}_{seed}_pitch{pitch:+.1f}", scene, spec)
    out = []
    for arm, overrides in (("base", base), ("set", new)):
        rep = run_job(config_from_dict(ss.case_config(case, work, work / "out" / arm, "fused", overrides)))
        records = rep.result.records
        learnt = sum(1 for r in records if r.is_keyframe and r.floor_normal_learnt)
        tilts = [r.floor_tilt_x_deg for r in records if r.floor_tilt_x_deg == r.floor_tilt_x_deg]
        calib = rep.result.wheel_calibration
        out.append((rep.accuracy.ate_se3_rmse_m if rep.accuracy is not None else float("nan"), learnt,
                    tilts[-1] if tilts else float("nan"), float("nan") if calib is None else calib.scale))
    return case.name, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the renders and the runs")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--base", action="append", metavar="K=V", help="the first setting's overrides (repeatable)")
    ap.add_argument("--set", action="append", metavar="K=V", help="the second's (repeatable)")
    args = ap.parse_args()
    base, new = tuple(args.base or ()), tuple(args.set or ())
    from windowvo.tools.scale_suite import study_args_error

    err = study_args_error(args.work, base, new)
    if err is not None:
        print(f"mount_study.py: error: {err}", file=sys.stderr)
        return 2
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        results = list(ex.map(run_case, [(args.work, c, base, new) for c in CASES]))
    ratios = []
    for name, ((a0, n0, t0, s0), (a1, n1, t1, s1)) in results:
        ratios.append(a1 / a0)
        print(f"{name:34s} ATE {a0:.4f} -> {a1:.4f} ({a1 / a0:.2f}x)  learnt normal at {n0} / {n1} keyframes  "
              f"learnt pitch {t0:+.2f} / {t1:+.2f} deg  wheel scale {s0:.4f} / {s1:.4f}")
    finite = [r for r in ratios if r > 0 and math.isfinite(r)]
    if finite:
        print(f"set / base: geometric mean {math.exp(sum(math.log(r) for r in finite) / len(finite)):.3f}x, "
              f"worst {max(finite):.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
