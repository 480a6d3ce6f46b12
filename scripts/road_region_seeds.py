"""Study (issue #26): two settings compared on rendered sequences the scale suite does not hold.

    python scripts/road_region_seeds.py --work DIR [--cases region|slip|streets|kitti|rocking|raised] [--jobs 2]
        [--base K=V ...] [--set K=V ...] [--seeds N] [--renders DIR]

``--cases region`` (the default; item 2, ``backend.ground.road_region``): renders 13 sequences (rooms and
warehouses 10 s, streets 8 s, wheels -2% to +2%, seeds 121-123, 221-226, 331-334) into DIR and runs each fused and
floor only, with and without the floor's region (docs/scale_suite.md, "The floor measured by region").
``--cases slip`` (item 3, ``backend.odometry.slip_switch``): 12 sequences whose wheels slip in two windows of
other times and sizes than the suite's (seeds 141-144, 241-244, 341-344), each run fused and wheels only, with and
without the switch (docs/scale_suite.md, "Slipping wheel steps switched off").
``--cases streets``: 10 more streets (8 s, wheels -3% to +3%, seeds 351-360), each run fused and floor only.
``--cases rocking``: 12 bases rocking on their suspension by 0.7-2 deg (rooms and warehouses 10 s, streets 8 s, wheels
-2% to +3%, seeds 161-164, 261-264, 361-364), each run fused and floor only, with the region's steps tied along their
ridge with the camera's tilt and without (``road_region.tilt_ridge_deg``).
``--cases raised``: 8 rooms and warehouses (10 s, wheels -2% to +3%, seeds 171-174, 271-274) with platforms or mats
1.5-4 cm high 0.5-1.0 m beside the path, each run fused and floor only, with the floor landmarks the base drives past
untied beside its track and without (``ground.corridor_heights`` 1.0).
``--cases kitti``: the two KITTI excerpts in ``../shared/data`` with synthetic wheels of the errors the scale suite
does not hold (-2%, -1%, +1%, +3%; its yaw bias), each run fused and wheels only (the second the same in both
settings: what the fused run must not be worse than).
``--base`` against ``--set``: any two settings instead. Prints each ATE SE(3) and the ratios' geometric mean and
worst per scene. ``--seeds N``: the ways that use the floor (fused, floor only) run with the floor plane's RANSAC
seeds 0 .. N-1 (``backend.ground.seed``, after the settings' own overrides, as the scale suite's ``--seeds``) and each
ATE is the median of the N runs: one run of a street moves by 2-4x with a fraction of a per cent in a step, and the
median judges a change by more than which corners one seed picked. ``--renders DIR``: where the sequences are
rendered and read from (default ``--work``), so that studies with their own ``--work`` share one set of renders.
"""

from __future__ import annotations

import argparse
import logging
import math
import statistics
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from windowvo.tools.bench import KITTI_EXCERPTS, SHARED_DATA

CASES = ([("warehouse", p, s, sc, 0.004) for p, s, sc in [("loop", 221, 0.01), ("figure_eight", 222, -0.02),
                                                           ("loop", 223, 0.02), ("figure_eight", 224, 0.01),
                                                           ("straight", 225, -0.01), ("loop", 226, -0.02)]]
         + [("street", p, s, sc, 0.002) for p, s, sc in [("loop", 331, 0.02), ("loop", 332, -0.01),
                                                          ("stop_and_go", 333, 0.02), ("straight", 334, -0.02)]]
         + [("room", p, s, sc, 0.005) for p, s, sc in [("loop", 121, 0.02), ("figure_eight", 122, -0.02),
                                                        ("straight", 123, 0.01)]])


# Slip windows (start s, end s, extra distance share) of other times and sizes than the suite's.
SLIP_WINDOWS = [[(2.5, 3.5, 0.3), (6.5, 8.0, 0.45)], [(3.0, 4.5, 0.5), (7.5, 8.5, 0.3)],
                [(4.0, 5.0, 0.35), (6.0, 7.5, 0.4)], [(2.0, 3.0, 0.45), (5.5, 6.5, 0.35)]]
SLIP_CASES = ([("room", p, s, sc, 0.006, w) for (p, s, sc), w in zip(
                  [("loop", 141, 0.01), ("figure_eight", 142, -0.02), ("loop", 143, -0.01), ("straight", 144, 0.02)],
                  SLIP_WINDOWS)]
              + [("warehouse", p, s, sc, 0.004, w) for (p, s, sc), w in zip(
                  [("loop", 241, 0.02), ("figure_eight", 242, 0.01), ("stop_and_go", 243, -0.02),
                   ("loop", 244, -0.01)], SLIP_WINDOWS)]
              + [("street", p, s, sc, 0.002, w) for (p, s, sc), w in zip(
                  [("loop", 341, 0.02), ("straight", 342, -0.01), ("loop", 343, -0.02), ("stop_and_go", 344, 0.01)],
                  SLIP_WINDOWS)])

# More streets (seeds the suite and the cases above do not hold): the fused street runs move by 2-4x either way with
# a fraction of a per cent in the region's steps, so a change to the region needs many of them to be judged.
STREET_CASES = [("street", p, s, sc, y) for p, s, sc, y in [
    ("straight", 351, 0.02, 0.002), ("loop", 352, -0.02, 0.005), ("stop_and_go", 353, 0.01, 0.002),
    ("straight", 354, -0.03, 0.004), ("loop", 355, 0.03, 0.002), ("loop", 356, -0.01, 0.003),
    ("straight", 357, 0.01, 0.008), ("loop", 358, 0.02, 0.002), ("stop_and_go", 359, -0.02, 0.005),
    ("straight", 360, 0.03, 0.002)]]

# Bases rocking on their suspension (roll and pitch of 0.7-2 deg, the renderer's vibration_deg) with seeds the suite
# does not hold: the suite has five such sequences.
ROCKING_CASES = [(scene, p, s, sc, y, [], vib) for scene, p, s, sc, y, vib in [
    ("room", "loop", 161, 0.02, 0.005, 1.0), ("room", "figure_eight", 162, -0.01, 0.003, 1.5),
    ("room", "straight", 163, -0.02, 0.004, 2.0), ("room", "figure_eight", 164, 0.03, 0.008, 0.8),
    ("warehouse", "loop", 261, -0.02, 0.004, 1.2), ("warehouse", "figure_eight", 262, 0.01, 0.006, 1.5),
    ("warehouse", "straight", 263, 0.02, 0.002, 0.8), ("warehouse", "stop_and_go", 264, -0.01, 0.004, 2.0),
    ("street", "straight", 361, 0.02, 0.002, 0.7), ("street", "loop", 362, -0.02, 0.003, 1.0),
    ("street", "stop_and_go", 363, 0.01, 0.002, 0.8), ("street", "loop", 364, 0.03, 0.004, 1.2)]]

# Platforms or mats beside the path (the renderer's kerb_height_m: 0.5 m squares 0.5-1.0 m either side), of heights and
# floor textures (floor_contrast; None: the scene's) the suite's two such sequences do not hold.
RAISED_CASES = [(scene, p, s, sc, 0.004, [], 0.0, kh, fc) for scene, p, s, sc, kh, fc in [
    ("room", "loop", 171, 0.02, 0.02, 0.3), ("room", "figure_eight", 172, -0.02, 0.04, 0.5),
    ("room", "straight", 173, 0.01, 0.025, 0.3), ("room", "loop", 174, -0.01, 0.035, 1.0),
    ("warehouse", "loop", 271, 0.02, 0.02, None), ("warehouse", "figure_eight", 272, -0.01, 0.015, None),
    ("warehouse", "straight", 273, 0.03, 0.03, None), ("warehouse", "stop_and_go", 274, -0.02, 0.02, None)]]

# The KITTI excerpts with the wheel errors the scale suite does not hold (its own are +2% and -3%): the suite's four
# KITTI runs include a cancellation (KITTI 06's road 3% nearer than configured, its wheels 2% long).
KITTI_CASES = [("kitti", name, 0, e, 0.0) for name in KITTI_EXCERPTS for e in (-0.02, -0.01, 0.01, 0.03)]

OFF = ("backend.ground.road_region.enabled=false",)
ON = ("backend.ground.road_region.enabled=true",)
SWITCH_OFF = ("backend.odometry.slip_switch=false",)
SWITCH_ON = ("backend.odometry.slip_switch=true",)
RIDGE_OFF = ("backend.ground.road_region.tilt_ridge_deg=0",)
RIDGE_ON = ("backend.ground.road_region.tilt_ridge_deg=0.1",)
CORRIDOR_OFF = ("backend.ground.corridor_heights=null",)
CORRIDOR_ON = ("backend.ground.corridor_heights=1.0",)
STUDIES = {"region": (CASES, ("fused", "floor"), OFF, ON), "slip": (SLIP_CASES, ("fused", "wheels"), SWITCH_OFF,
                                                                      SWITCH_ON),
           "streets": (STREET_CASES, ("fused", "floor"), OFF, ON),
           "kitti": (KITTI_CASES, ("fused", "wheels"), OFF, ON),
           "rocking": (ROCKING_CASES, ("fused", "floor"), RIDGE_OFF, RIDGE_ON),
           "raised": (RAISED_CASES, ("fused", "floor"), CORRIDOR_OFF, CORRIDOR_ON)}


def run_seeds(way: str, seeds: int, seeded_ways: tuple[str, ...]) -> list[int | None]:
    """The floor RANSAC seeds one way of one setting runs with: 0 .. seeds-1 for a way that uses the floor, when
    ``seeds`` is above 1; else one run at the config's seed (None)."""
    return list(range(seeds)) if seeds > 1 and way in seeded_ways else [None]


def median(xs: list[float]) -> float:
    """The median of the finite values (nan if none: a run without an ATE)."""
    finite = [x for x in xs if math.isfinite(x)]
    return statistics.median(finite) if finite else float("nan")


def run_case(args: tuple[Path, Path, tuple, tuple[str, ...], tuple[str, ...], tuple[str, ...], int]
             ) -> tuple[str, list[float]]:
    """ATE SE(3) of (first way base, first way set, second way base, second way set), each the median over the
    seeds' runs."""
    work, renders, (scene, path, seed, scale, yaw, *extra), ways, base, new, seeds = args
    slip, vibration_deg = (extra[0] if extra else []), (extra[1] if len(extra) > 1 else 0.0)
    kerb_m, floor_contrast = (extra[2] if len(extra) > 2 else 0.0), (extra[3] if len(extra) > 3 else None)
    logging.disable(logging.WARNING)
    from windowvo.config import config_from_dict
    from windowvo.runtime.job import run_job
    from windowvo.tools import scale_suite as ss

    if scene == "kitti":
        case = ss.ScaleCase(f"{path}_wheels{100 * scale:+.0f}pct", scene, {}, kitti_path=SHARED_DATA / path,
                            kitti_wheel_scale_error=scale)
    else:
        spec: dict = {"path": path, "seed": seed, "duration_s": 8.0 if scene == "street" else 10.0,
                      "vibration_deg": vibration_deg,
                      "wheel": {"scale_error": scale, "yaw_bias_per_m": yaw, "slip_windows": slip}}
        if scene == "street":
            spec.update(ss.STREET_IMAGE)
        if kerb_m > 0:
            spec["kerb_height_m"] = kerb_m
        if floor_contrast is not None:
            spec["floor_contrast"] = floor_contrast
        name = (f"{scene}_{path}_{seed}" + ("_rocking" if vibration_deg > 0 else "")
                + (f"_raised{1000 * kerb_m:.0f}mm" if kerb_m > 0 else ""))
        case = ss.ScaleCase(name, scene, spec)
    ates = []
    for way in ways:
        for arm, overrides in (("base", base), ("set", new)):
            runs = []
            for seed_i in run_seeds(way, seeds, ss.SEEDED_WAYS):
                rep = run_job(config_from_dict(ss.case_config(case, renders, work / "out" / arm, way, overrides,
                                                              seed_i)))
                runs.append(rep.accuracy.ate_se3_rmse_m if rep.accuracy is not None else float("nan"))
            ates.append(median(runs))
    return case.name, ates


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the runs (and the renders)")
    ap.add_argument("--renders", type=Path, help="folder the sequences are rendered into and read from (default: "
                    "--work)")
    ap.add_argument("--seeds", type=int, default=1, help="the floor's RANSAC seeds each fused and floor-only ATE is "
                    "the median over (default 1: one run)")
    ap.add_argument("--cases", choices=sorted(STUDIES), default="region", help="which study's sequences")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--base", action="append", metavar="K=V", help="the first setting's overrides (repeatable; "
                    "default: the region off, or the slip switch off)")
    ap.add_argument("--set", action="append", metavar="K=V", help="the second's (default: the region on, or the "
                    "slip switch on)")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        print(f"road_region_seeds.py: error: --seeds must be at least 1 (got {args.seeds})", file=sys.stderr)
        return 2
    cases, ways, off, on = STUDIES[args.cases]
    if args.cases == "kitti" and not all((SHARED_DATA / n).is_dir() for n in KITTI_EXCERPTS):
        print(f"road_region_seeds.py: error: the KITTI excerpts are not in {SHARED_DATA}", file=sys.stderr)
        return 2
    base, new = tuple(args.base or off), tuple(args.set or on)
    from windowvo.tools.scale_suite import study_args_error

    renders = args.renders if args.renders is not None else args.work
    err = study_args_error(args.work, base, new) or study_args_error(renders)
    if err is not None:
        print(f"road_region_seeds.py: error: {err}", file=sys.stderr)
        return 2
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        results = list(ex.map(run_case, [(args.work, renders, c, ways, base, new, args.seeds) for c in cases]))
    if args.seeds > 1:
        print(f"(fused and floor only: each the median of {args.seeds} seeds of the floor's RANSAC)")
    for name, (f0, f1, g0, g1) in results:
        print(f"{name:28s} {ways[0]} {f0:.3f} -> {f1:.3f} ({f1 / f0:.2f}x)  {ways[1]} only {g0:.3f} -> {g1:.3f} "
              f"({g1 / g0:.2f}x)")
    for scene in ("warehouse", "street", "room", "kitti"):
        fused = [v[1] / v[0] for n, v in results if n.startswith(scene)]
        floor = [v[3] / v[2] for n, v in results if n.startswith(scene)]
        if not fused:
            continue
        if scene == "kitti":
            worse = [sum(v[i] > v[2 + i] for n, v in results if n.startswith(scene)) for i in (0, 1)]
            print(f"kitti: {ways[0]} worse than {ways[1]} only: {worse[0]} of {len(fused)} -> {worse[1]}")

        def gmean(xs: list[float]) -> float:
            return math.exp(sum(map(math.log, xs)) / len(xs))

        print(f"{scene}: {ways[0]} {gmean(fused):.2f}x (worst {max(fused):.2f}x), {ways[1]} only "
              f"{gmean(floor):.2f}x (worst {max(floor):.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
