"""The scale suite: do fused metric cues ever do worse than one cue alone? (issue #26)

Every sequence runs four ways, the same code and data, only the cue set changing:

* ``fused``: wheels (calibrated online) and the floor at the camera height, the defaults;
* ``floor``: the floor only (``backend.use_odometry=false``);
* ``wheels``: the wheels only (``backend.ground.enabled=false``);
* ``none``: neither (a monocular run, up to scale: Sim(3) only);

plus the wheels alone (dead reckoning). The sequences vary what the estimator does not assume: rendered
rooms, warehouses (camera 0.4 m, shiny low-texture floor, a person walking) and streets (camera 1.65 m,
10 m/s, kerbs, parked cars), wheels with +-1-3% scale, 0.002-0.015 rad/m yaw bias, 0-5% track-width
error and slip, some on a rocking base, and the KITTI excerpts with +2% and -3% synthetic wheels. None
of the wheel errors is told to the estimator.

The table gives SE(3) and Sim(3) ATE per way and the ratio fused / best single cue (the better of
``floor`` and ``wheels`` in SE(3)); the summary gives its geometric mean and worst case, the share of
sequences within 1.1x, and fused SE(3) / Sim(3). Numbers are what this machine measured; nothing is
enforced here (the regression tests hold the bounds).

One run of a way moves by chance: the floor plane's RANSAC (``backend.ground.seed``) alone moves the floor-only
way's ATE by more than 10% on about half of the sequences (docs/scale_suite.md). With ``seeds`` N > 1 the ways that
use the floor (fused, floor) run with the seeds 0 .. N-1 and each way's ATE is the median of its runs (their
spread is in the row: ``seed_spread``, the largest over the smallest), so the ratios compare medians.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .bench import KITTI_EXCERPTS, SHARED_DATA

# The ways whose runs depend on the floor plane's RANSAC seed (the others do not use the floor).
SEEDED_WAYS = ("fused", "floor")
SEED_KEY = "backend.ground.seed"
# The four ways each sequence runs: config overrides on top of the defaults.
WAYS: dict[str, list[str]] = {
    "fused": [],
    "floor": ["backend.use_odometry=false"],
    "wheels": ["backend.ground.enabled=false"],
    "none": ["backend.use_odometry=false", "backend.ground.enabled=false"],
}
# Rendered sequences: seconds, and the street's image (half of KITTI's 1226x370, the same field of view).
DURATION_S = 15.0
STREET_IMAGE = {"width": 613, "height": 185, "fx": 353.5}
KITTI_WHEEL_SCALE_ERRORS = (0.02, -0.03)
KITTI_SCALE_SUITE_YAW_BIAS_PER_M = 0.002


@dataclass(frozen=True)
class ScaleCase:
    """One sequence of the suite: a rendered scene (``spec``: SynthSpec fields) or a KITTI excerpt."""

    name: str
    scene: str  # room | warehouse | street | kitti
    spec: dict = field(default_factory=dict)
    kitti_path: Path | None = None
    kitti_wheel_scale_error: float = 0.0


def _wheel(scale: float, yaw: float = 0.005, track: float = 0.0, slip: bool = False) -> dict:
    windows = [(4.0, 5.5, 0.4), (10.0, 11.0, 0.5)] if slip else []
    return {"scale_error": scale, "yaw_bias_per_m": yaw, "yaw_scale_error": track, "slip_windows": windows}


def rendered_cases() -> list[ScaleCase]:
    """Rooms, warehouses and streets with wheel errors the estimator does not model."""
    room = [
        ("room_loop_+1pct_slip", dict(path="loop", seed=101), _wheel(0.01, 0.012, slip=True)),
        ("room_loop_-3pct", dict(path="loop", seed=102), _wheel(-0.03, 0.002)),
        ("room_fig8_+2pct_track3pct", dict(path="figure_eight", seed=103), _wheel(0.02, 0.005, 0.03)),
        ("room_fig8_rocking_-1pct", dict(path="figure_eight", seed=104, vibration_deg=1.5), _wheel(-0.01)),
        ("room_straight_+3pct", dict(path="straight", seed=105), _wheel(0.03, 0.008)),
        ("room_stopgo_-2pct_track5pct", dict(path="stop_and_go", seed=106), _wheel(-0.02, 0.004, 0.05)),
        ("room_kerbs_+2pct", dict(path="loop", seed=107, kerb_height_m=0.03, floor_contrast=0.3), _wheel(0.02)),
        ("room_loop_rocking_+2pct", dict(path="loop", seed=108, vibration_deg=1.0), _wheel(0.02, 0.01)),
        ("room_fig8_yaw15mrad_-1pct", dict(path="figure_eight", seed=109), _wheel(-0.01, 0.015)),
        ("room_loop_slip_-1pct", dict(path="loop", seed=110), _wheel(-0.01, 0.006, slip=True)),
        ("room_fig8_-1pct_track-3pct", dict(path="figure_eight", seed=111), _wheel(-0.01, 0.003, -0.03)),
    ]
    warehouse = [
        ("warehouse_loop_+1pct", dict(path="loop", seed=201), _wheel(0.01, 0.004)),
        ("warehouse_fig8_-2pct", dict(path="figure_eight", seed=202), _wheel(-0.02, 0.008)),
        ("warehouse_straight_+3pct_track2pct", dict(path="straight", seed=203), _wheel(0.03, 0.002, 0.02)),
        ("warehouse_loop_rocking_-3pct", dict(path="loop", seed=204, vibration_deg=1.0), _wheel(-0.03, 0.005)),
        ("warehouse_stopgo_+2pct_slip", dict(path="stop_and_go", seed=205), _wheel(0.02, 0.006, slip=True)),
        ("warehouse_fig8_yaw10mrad_+1pct", dict(path="figure_eight", seed=206), _wheel(0.01, 0.010)),
        ("warehouse_loop_mats_+2pct", dict(path="loop", seed=207, kerb_height_m=0.02), _wheel(0.02, 0.004)),
    ]
    street = [
        ("street_straight_+2pct", dict(path="straight", seed=301), _wheel(0.02, 0.002)),
        ("street_straight_-3pct", dict(path="straight", seed=302), _wheel(-0.03, 0.003)),
        ("street_curve_+1pct", dict(path="loop", seed=303), _wheel(0.01, 0.002)),
        ("street_curve_-2pct_track3pct", dict(path="loop", seed=304), _wheel(-0.02, 0.002, 0.03)),
        ("street_stopgo_+3pct", dict(path="stop_and_go", seed=305), _wheel(0.03, 0.004)),
        ("street_straight_rocking_-1pct", dict(path="straight", seed=306, vibration_deg=0.7), _wheel(-0.01, 0.002)),
        ("street_curve_slip_+2pct", dict(path="loop", seed=307), _wheel(0.02, 0.003, slip=True)),
        ("street_straight_kerb10cm_+1pct", dict(path="straight", seed=308, kerb_height_m=0.10), _wheel(0.01)),
        ("street_curve_rocking_+2pct", dict(path="loop", seed=309, vibration_deg=0.7), _wheel(0.02, 0.002)),
    ]
    out = [ScaleCase(n, "room", {**s, "wheel": w}) for n, s, w in room]
    out += [ScaleCase(n, "warehouse", {**s, "wheel": w}) for n, s, w in warehouse]
    out += [ScaleCase(n, "street", {**s, **STREET_IMAGE, "wheel": w}) for n, s, w in street]
    return out


def kitti_scale_cases() -> list[ScaleCase]:
    """Each KITTI excerpt (when ``../shared/data`` is there) with +2% and -3% synthetic wheels."""
    out = []
    for name in KITTI_EXCERPTS:
        if (SHARED_DATA / name).is_dir():
            out += [ScaleCase(f"{name}_wheels{100 * e:+.0f}pct", "kitti", kitti_path=SHARED_DATA / name,
                              kitti_wheel_scale_error=e) for e in KITTI_WHEEL_SCALE_ERRORS]
    return out


def suite_cases() -> list[ScaleCase]:
    return rendered_cases() + kitti_scale_cases()


def synth_spec(case: ScaleCase):
    """The SynthSpec of a rendered case (its scene's defaults where the case leaves them)."""
    from ..synth.generate import SynthSpec, WheelErrorModel
    from ..synth.paths import PathKind
    from ..synth.scenes import SceneKind

    fields = dict(case.spec)
    fields["wheel"] = WheelErrorModel(**fields["wheel"])
    fields["path"] = PathKind(fields["path"])
    fields.setdefault("duration_s", DURATION_S)
    return SynthSpec.for_scene(SceneKind(case.scene), **fields)


def ensure_rendered(case: ScaleCase, cache: Path) -> Path:
    """Render a case once into the cache (reused by later runs)."""
    from ..synth.generate import generate_sequence

    seq_dir = cache / case.name
    if not (seq_dir / "synth.json").is_file():
        generate_sequence(seq_dir, synth_spec(case))
    return seq_dir


def study_args_error(work: Path, *settings: tuple[str, ...]) -> str | None:
    """The one-line error of a study's work folder (created here) or of its settings' config overrides (checked on a
    stand-in config before any render, so that a bad key is refused at once and not in a worker), or None."""
    from ..config import apply_overrides, config_from_dict
    from ..errors import WindowVOError

    try:
        work.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        return f"cannot use {work}: {err.strerror}"
    for overrides in settings:
        try:
            config_from_dict(apply_overrides({"sequence": str(work), "output": str(work / "check")}, list(overrides)))
        except WindowVOError as err:
            return str(err)
    return None


def case_config(case: ScaleCase, cache: Path, out: Path, way: str, overrides: tuple[str, ...] = (),
                seed: int | None = None) -> dict:
    """The config mapping of one way of one case (sequential, no recording); ``overrides`` (``dotted.key=value``,
    as on the run's command line) change every way, and the way's own cue switches are applied after them.
    ``seed``: the floor plane's RANSAC seed of this run (its outputs in ``<way>/seed<seed>``); None: the config's."""
    from ..config import apply_overrides

    folder = out / case.name / way if seed is None else out / case.name / way / f"seed{seed}"
    data: dict[str, Any] = {"progress": False, "viz": {"rerun": "off"}, "run_mode": "sequential",
                            "output": str(folder)}
    if case.kitti_path is not None:
        data.update(sequence=str(case.kitti_path), dataset="kitti",
                    odometry_synthesis={"enabled": True, "scale_error": case.kitti_wheel_scale_error,
                                        "yaw_bias_per_m": KITTI_SCALE_SUITE_YAW_BIAS_PER_M})
    else:
        data["sequence"] = str(ensure_rendered(case, cache))
    seeded = [] if seed is None else [f"{SEED_KEY}={seed}"]
    return apply_overrides(apply_overrides(data, [*overrides, *seeded]), list(WAYS[way]))


def _ate(acc) -> dict:
    if acc is None:
        return {"se3": float("nan"), "sim3": float("nan"), "path_m": float("nan")}
    return {"se3": float("nan") if acc.monocular else acc.ate_se3_rmse_m, "sim3": acc.ate_sim3_rmse_m,
            "path_m": acc.path_length_m}


def _median_of_runs(runs: list[dict]) -> dict:
    """One way's entry from its runs (one per seed): the median ATEs, each run's, and their spread."""
    if len(runs) == 1:
        return runs[0]
    se3 = [r["se3"] for r in runs]
    finite = [v for v in se3 if math.isfinite(v) and v > 0]
    return {**runs[0], "se3": float(np.median(se3)), "sim3": float(np.median([r["sim3"] for r in runs])),
            "se3_runs": se3, "seed_spread": max(finite) / min(finite) if finite else float("nan")}


def run_scale_case(case: ScaleCase, cache: Path, out: Path, overrides: tuple[str, ...] = (), seeds: int = 1) -> dict:
    """One sequence, four ways and the wheels alone (runs in a worker process); with ``seeds`` above 1 the ways
    that use the floor run once per seed and give their medians (``_median_of_runs``)."""
    logging.basicConfig(level=logging.ERROR)
    from ..config import config_from_dict
    from ..eval.metrics import evaluate
    from ..runtime.job import run_job, wheel_only_trajectory

    row: dict[str, Any] = {"sequence": case.name, "scene": case.scene}
    rep = None
    for way in WAYS:
        runs, scales = [], []
        for seed in (range(seeds) if seeds > 1 and way in SEEDED_WAYS else [None]):
            rep = run_job(config_from_dict(case_config(case, cache, out, way, overrides, seed)))
            runs.append({**_ate(rep.accuracy), "metric": rep.result.metric, "scale_sources": rep.result.scale_sources})
            c = rep.result.wheel_calibration
            scales.append(float("nan") if c is None else c.scale)
        row[way] = _median_of_runs(runs)
        if way == "fused":
            row["wheel_scale_estimated"] = None if all(math.isnan(v) for v in scales) else float(np.nanmedian(scales))
    assert rep is not None and rep.sequence.groundtruth is not None
    wheel = wheel_only_trajectory(rep.sequence, rep.result.trajectory.timestamps)
    row["wheels_alone"] = _ate(evaluate(rep.sequence.groundtruth, wheel)) if wheel is not None else _ate(None)
    best = min(row["floor"]["se3"], row["wheels"]["se3"])
    row["fused_over_best"] = row["fused"]["se3"] / best if best > 0 else float("nan")
    row["fused_se3_over_sim3"] = (row["fused"]["se3"] / row["fused"]["sim3"]
                                  if row["fused"]["sim3"] > 0 else float("nan"))
    return row


def run_suite(cases: list[ScaleCase], cache: Path, out: Path, jobs: int, overrides: tuple[str, ...] = (),
              seeds: int = 1) -> list[dict]:
    """Render every case first (in this process), then each case in a fresh interpreter, ``jobs`` at once
    (``overrides``: see :func:`case_config`; ``seeds``: :func:`run_scale_case`)."""
    from .executors import values_in_processes

    for c in cases:
        if c.kitti_path is None:
            ensure_rendered(c, cache)
    return values_in_processes([(c.name, run_scale_case, (c, cache, out, tuple(overrides), seeds)) for c in cases],
                               jobs, "scale suite")


def gmean(values: list[float]) -> float:
    """Geometric mean of the positive, finite values (nan for none)."""
    v = [x for x in values if x > 0 and math.isfinite(x)]
    return float(np.exp(np.mean(np.log(v)))) if v else float("nan")


def summary(rows: list[dict]) -> dict:
    """The distribution over the suite: fused / best single cue, fused / wheels alone, fused SE(3) / Sim(3)."""
    ratios = [r["fused_over_best"] for r in rows]
    finite = [x for x in ratios if math.isfinite(x)]
    vs_wheels = [r["fused"]["se3"] / r["wheels_alone"]["se3"] for r in rows if r["wheels_alone"]["se3"] > 0]
    kitti = [r["fused_se3_over_sim3"] for r in rows if r["scene"] == "kitti"]
    return {
        "sequences": len(rows),
        "fused_over_best_gmean": gmean(ratios),
        "fused_over_best_worst": max(finite) if finite else float("nan"),
        "share_within_1.1x": sum(x <= 1.1 for x in finite) / len(finite) if finite else float("nan"),
        "share_within_1.5x": sum(x <= 1.5 for x in finite) / len(finite) if finite else float("nan"),
        "fused_worse_than_wheels_alone": sum(x > 1.0 for x in vs_wheels),
        "fused_se3_over_sim3_gmean": gmean([r["fused_se3_over_sim3"] for r in rows]),
        "kitti_fused_se3_over_sim3_worst": max(kitti) if kitti else float("nan"),
        "seeds": max((len(r[w].get("se3_runs", [0])) for r in rows for w in SEEDED_WAYS), default=1),
        # each seeded way: the share of sequences whose runs over the seeds lie within 1.1x of each other
        **{f"{w}_seed_spread_within_1.1x": _share_within(
            [r[w]["seed_spread"] for r in rows if "seed_spread" in r[w]], 1.1) for w in SEEDED_WAYS},
    }


def _share_within(values: list[float], bound: float) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return sum(v <= bound for v in finite) / len(finite) if finite else float("nan")


def _m(v: float) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.3f}"


def table(rows: list[dict]) -> str:
    head = ("| sequence | fused SE(3) / Sim(3) m | floor only | wheels only | no metric cue Sim(3) | wheels alone | "
            "fused / best single cue |\n|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        lines.append(f"| {r['sequence']} | {_m(r['fused']['se3'])} / {_m(r['fused']['sim3'])} | "
                     f"{_m(r['floor']['se3'])} / {_m(r['floor']['sim3'])} | "
                     f"{_m(r['wheels']['se3'])} / {_m(r['wheels']['sim3'])} | {_m(r['none']['sim3'])} | "
                     f"{_m(r['wheels_alone']['se3'])} | {r['fused_over_best']:.2f}x |")
    return "\n".join(lines)


def summary_text(s: dict) -> str:
    seeds = s.get("seeds", 1)
    chance = "" if seeds <= 1 else (
        f" (each way's median over {seeds} seeds of the floor's RANSAC; a way's runs within 1.1x of each other: "
        + ", ".join(f"{w} {100 * s[f'{w}_seed_spread_within_1.1x']:.0f}%" for w in SEEDED_WAYS) + " of the sequences)")
    return (f"{s['sequences']} sequences{chance}: fused / best single cue geometric mean {s['fused_over_best_gmean']:.2f}x, "
            f"worst {s['fused_over_best_worst']:.2f}x, within 1.1x on {100 * s['share_within_1.1x']:.0f}%, within "
            f"1.5x on {100 * s['share_within_1.5x']:.0f}%; fused worse than the wheels alone on "
            f"{s['fused_worse_than_wheels_alone']}; fused SE(3) / Sim(3) geometric mean "
            f"{s['fused_se3_over_sim3_gmean']:.2f}x (KITTI worst {s['kitti_fused_se3_over_sim3_worst']:.2f}x)")


def write_results(rows: list[dict], out: Path) -> dict:
    s = summary(rows)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scale_suite.json").write_text(json.dumps({"rows": rows, "summary": s}, indent=2, default=float))
    return s
