"""Study (issue #26 item 2): ``backend.ground.road_region`` on rendered sequences the scale suite does not hold.

    python scripts/road_region_seeds.py --work DIR [--jobs 2] [--base K=V ...] [--set K=V ...]

Renders 13 sequences (rooms and warehouses 10 s, streets 8 s, wheels -2% to +2%, seeds 121-123, 221-226, 331-334)
into DIR and runs each fused and floor only, with and without the floor's region (or with the overrides ``--base``
against ``--set``: two settings compared); prints each ATE SE(3) and the ratios' geometric mean and worst per scene
(docs/scale_suite.md, "The floor measured by region").
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

CASES = ([("warehouse", p, s, sc, 0.004) for p, s, sc in [("loop", 221, 0.01), ("figure_eight", 222, -0.02),
                                                           ("loop", 223, 0.02), ("figure_eight", 224, 0.01),
                                                           ("straight", 225, -0.01), ("loop", 226, -0.02)]]
         + [("street", p, s, sc, 0.002) for p, s, sc in [("loop", 331, 0.02), ("loop", 332, -0.01),
                                                          ("stop_and_go", 333, 0.02), ("straight", 334, -0.02)]]
         + [("room", p, s, sc, 0.005) for p, s, sc in [("loop", 121, 0.02), ("figure_eight", 122, -0.02),
                                                        ("straight", 123, 0.01)]])


OFF = ("backend.ground.road_region.enabled=false",)
ON = ("backend.ground.road_region.enabled=true",)


def run_case(args: tuple[Path, tuple[str, str, int, float, float], tuple[str, ...], tuple[str, ...]]
             ) -> tuple[str, list[float]]:
    """ATE SE(3) of (fused base, fused set, floor base, floor set)."""
    work, (scene, path, seed, scale, yaw), base, new = args
    logging.disable(logging.WARNING)
    from windowvo.config import config_from_dict
    from windowvo.runtime.job import run_job
    from windowvo.tools import scale_suite as ss

    spec: dict = {"path": path, "seed": seed, "duration_s": 8.0 if scene == "street" else 10.0,
                  "wheel": {"scale_error": scale, "yaw_bias_per_m": yaw}}
    if scene == "street":
        spec.update(ss.STREET_IMAGE)
    case = ss.ScaleCase(f"{scene}_{path}_{seed}", scene, spec)
    ates = []
    for way in ("fused", "floor"):
        for arm, overrides in (("base", base), ("set", new)):
            data = ss.case_config(case, work, work / "out" / arm, way, overrides)
            rep = run_job(config_from_dict(data))
            ates.append(rep.accuracy.ate_se3_rmse_m if rep.accuracy is not None else float("nan"))
    return case.name, ates


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the renders and the runs")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--base", action="append", metavar="K=V", help="the first setting's overrides (repeatable; "
                    "default: the region off)")
    ap.add_argument("--set", action="append", metavar="K=V", help="the second's (default: the region on)")
    args = ap.parse_args()
    try:
        args.work.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"road_region_seeds.py: error: cannot use {args.work}: {err.strerror}", file=sys.stderr)
        return 2
    base, new = tuple(args.base or OFF), tuple(args.set or ON)
    from windowvo.config import apply_overrides, config_from_dict
    from windowvo.errors import WindowVOError

    for overrides in (base, new):  # refused here, in one line, not in a worker after the renders
        try:
            config_from_dict(apply_overrides({"sequence": str(args.work), "output": str(args.work / "check")},
                                             list(overrides)))
        except WindowVOError as err:
            print(f"road_region_seeds.py: error: {err}", file=sys.stderr)
            return 2
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        results = list(ex.map(run_case, [(args.work, c, base, new) for c in CASES]))
    for name, (f0, f1, g0, g1) in results:
        print(f"{name:28s} fused {f0:.3f} -> {f1:.3f} ({f1 / f0:.2f}x)  floor only {g0:.3f} -> {g1:.3f} "
              f"({g1 / g0:.2f}x)")
    for scene in ("warehouse", "street", "room"):
        fused = [v[1] / v[0] for n, v in results if n.startswith(scene)]
        floor = [v[3] / v[2] for n, v in results if n.startswith(scene)]

        def gmean(xs: list[float]) -> float:
            return math.exp(sum(map(math.log, xs)) / len(xs))

        print(f"{scene}: fused {gmean(fused):.2f}x (worst {max(fused):.2f}x), floor only {gmean(floor):.2f}x "
              f"(worst {max(floor):.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
