"""The wheel clock offset, estimated and applied, measured: each sequence run with its wheel stamps shifted.

For each sequence and offset, ``odometry.csv``'s stamps alone are shifted by the offset (the wheels' clock ahead of
the camera's by that much; the images are linked, not copied) and the sequence is run the fused way in the
sequential run mode twice: with ``backend.odometry.time_offset: estimate`` (the default: estimated and applied) and
``off`` (estimated, reported, the wheels read at the camera's times). It prints, per run, the estimate's error
against the true offset, its sigma, whether it was applied and from when, and the ATE SE(3) over the unshifted
sequence's run with the default config; then the geometric mean and the worst of those ratios for the offsets that are not zero.
With the defaults a run whose estimate was applied part way is made again from its first frame with it (a second
pass, ``backend.odometry.time_offset_second_pass``): "applied from" is then the first pass's time, marked "(2nd
pass)", and the ATE the second pass's; ``--set backend.odometry.time_offset_second_pass=false`` measures one pass.

    python scripts/wheel_clock_sweep.py SEQ [SEQ ...] --work DIR [--offsets-ms 0,15,30,50,-20] [--set KEY=VALUE ...]

``--set`` (repeatable) changes every run's config, e.g. to compare two settings of the wheel model, each in its own
``--work`` folder. Results in DIR/wheel_clock_sweep.json (runs already there are not repeated; a folder holds the
runs of one set of overrides).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from windowvo.config import apply_overrides, config_from_dict
from windowvo.errors import WindowVOError
from windowvo.runtime.job import run_job
from windowvo.synth.generate import shift_wheel_clock

MODES = ("estimate", "off")


def shifted(seq: Path, offset_ms: float, work: Path) -> Path:
    """``seq`` with its wheel stamps shifted by ``offset_ms`` (a folder in ``work``, made once; images linked)."""
    if offset_ms == 0:
        return seq
    out = work / "sequences" / f"{seq.name}_{offset_ms:+.0f}ms"
    return out if out.exists() else shift_wheel_clock(seq, out, offset_ms / 1000.0)


def run_once(seq: Path, mode: str, out: Path, overrides: list[str] | None = None) -> dict:
    data = apply_overrides({"sequence": str(seq), "output": str(out), "progress": False, "viz": {"rerun": "off"},
                            "run_mode": "sequential"}, [*(overrides or []), f"backend.odometry.time_offset={mode}"])
    report = run_job(config_from_dict(data))
    c = report.result.wheel_time_offset
    assert report.accuracy is not None and c is not None, "the sweep needs ground truth and wheels"
    first = report.result.first_pass_clock  # a second pass: when the first pass applied its estimate
    return {"ate": report.accuracy.ate_se3_rmse_m,
            "estimate_ms": 1000.0 * c.offset_s if c.observable else None, "sigma_ms": 1000.0 * c.sigma_s,
            "applied_ms": None if c.applied_s is None else 1000.0 * c.applied_s,
            "since_s": c.applied_since_t if first is None else first.applied_since_t, "second_pass": first is not None}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sequences", nargs="+", type=Path)
    p.add_argument("--work", type=Path, required=True, help="folder for the shifted sequences, runs and results")
    p.add_argument("--offsets-ms", default="0,15,30,50,-20", help="comma-separated offsets (ms); 0 is always run")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every run (repeatable; the time_offset mode of each run still applies)")
    a = p.parse_args()
    try:  # a bad key or value: one line, exit 2, before anything runs
        config_from_dict(apply_overrides({"sequence": ".", "output": str(a.work), "progress": False}, list(a.set)))
    except WindowVOError as err:
        print(f"wheel_clock_sweep: error: {err}", file=sys.stderr)
        return 2
    for seq in a.sequences:  # bad input: one line, exit 2
        missing = [n for n in ("odometry.csv", "groundtruth.txt") if not (seq / n).is_file()]
        if missing:
            print(f"wheel_clock_sweep: error: {seq} has no {' and no '.join(missing)} (a native sequence with wheels "
                  "and ground truth is needed)", file=sys.stderr)
            return 2
    logging.basicConfig(level=logging.ERROR)
    offsets = sorted({0.0, *(float(x) for x in a.offsets_ms.split(","))}, key=lambda x: (x != 0, x))
    a.work.mkdir(parents=True, exist_ok=True)
    store = a.work / "wheel_clock_sweep.json"
    res = json.loads(store.read_text()) if store.exists() else {}
    if res.setdefault("overrides", list(a.set)) != list(a.set):
        print(f"wheel_clock_sweep: error: {a.work} holds runs made with --set {res['overrides'] or '(none)'}; "
              "use another --work for other overrides", file=sys.stderr)
        return 2
    ratios: dict[str, list[float]] = {m: [] for m in MODES}
    print("| sequence | offset ms | estimate error ms (sigma) | applied from s | ATE m estimate / off | "
          "over plain: estimate / off |\n|---|---|---|---|---|---|")
    for seq in a.sequences:
        for off in offsets:
            for mode in MODES:
                key = f"{seq.name}|{off:+.0f}|{mode}"
                if key not in res:
                    res[key] = run_once(shifted(seq, off, a.work), mode, a.work / "runs" / key.replace("|", "_"), a.set)
                    store.write_text(json.dumps(res, indent=1))
            plain = res[f"{seq.name}|+0|estimate"]["ate"]  # the same run (default config) without the offset
            est, off_run = res[f"{seq.name}|{off:+.0f}|estimate"], res[f"{seq.name}|{off:+.0f}|off"]
            err = "not observable" if est["estimate_ms"] is None else \
                f"{est['estimate_ms'] - off:+.1f} ({est['sigma_ms']:.1f})"
            since = "-" if est["since_s"] is None else f"{est['since_s']:.1f}"
            if est.get("second_pass"):
                since += " (2nd pass)"
            if off != 0:
                ratios["estimate"].append(est["ate"] / plain)
                ratios["off"].append(off_run["ate"] / plain)
            print(f"| {seq.name} | {off:+.0f} | {err} | {since} | {est['ate']:.4f} / {off_run['ate']:.4f} | "
                  f"{est['ate'] / plain:.2f}x / {off_run['ate'] / plain:.2f}x |")
    for mode, r in ratios.items():
        if r:
            g = math.exp(sum(math.log(x) for x in r) / len(r))
            within = sum(x <= 1.05 for x in r)
            print(f"{mode}: over the plain run, offsets not 0: gmean {g:.2f}x, worst {max(r):.2f}x, "
                  f"{within} of {len(r)} within 1.05x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
