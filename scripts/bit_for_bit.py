"""Bit-for-bit check of a refactoring: run the benchmark's sequences through ``python -m windowvo.run``
and compare every output with a reference run, timing fields aside.

    python scripts/bit_for_bit.py run OUT_DIR [--cache DIR] [--duration 30]   # run every case into OUT_DIR
    python scripts/bit_for_bit.py compare REF_DIR NEW_DIR                     # exit 1 on any difference

Each case runs sequentially and, for the plain loop and one KITTI excerpt, pipelined as well (the
worker mode has its own code path). Compared: trajectory.txt, trajectory_online.txt, stats.csv
(without the ms columns), summary.json (without wall time, fps and ms), config_resolved.yaml.
Uses only the command line and the benchmark's case list, so the same script runs before and after.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import yaml

TIMING_COLUMNS = {"frontend_ms", "backend_ms", "latency_ms"}
TIMING_KEYS = {"wall_s", "fps", "frontend_ms_mean", "backend_ms_median"}
FILES = ("trajectory.txt", "trajectory_online.txt", "stats.csv", "summary.json", "config_resolved.yaml")


def _bench():
    try:
        from windowvo.tools import bench  # after the restructuring
    except ImportError:
        from windowvo import bench  # type: ignore[no-redef]
    return bench


def run(out: Path, cache: Path, duration: float) -> None:
    bench = _bench()
    cases = bench.synthetic_cases(duration) + bench.kitti_cases()
    pipelined = {"loop", "kitti06_000-050"}
    for case in cases:
        for mode in ("sequential", "pipelined") if case.name in pipelined else ("sequential",):
            name = f"{case.name}__{mode}"
            data = bench.case_config_data(case, cache, out / "runs", overrides=(f"run_mode={mode}",))
            data["output"] = str(out / "runs" / name)
            cfg_path = out / "configs" / f"{name}.yaml"
            cfg_path.parent.mkdir(parents=True, exist_ok=True)
            cfg_path.write_text(yaml.safe_dump(data))
            res = subprocess.run([sys.executable, "-m", "windowvo.run", str(cfg_path)], capture_output=True, text=True)
            print(f"{name}: rc {res.returncode}", flush=True)


def _summary(path: Path) -> dict:
    def strip(d):
        if isinstance(d, dict):
            return {k: strip(v) for k, v in d.items() if k not in TIMING_KEYS}
        return d
    return strip(json.loads(path.read_text()))


def _stats(path: Path) -> list[dict]:
    with path.open() as fh:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in csv.DictReader(fh)]


def _config(path: Path) -> dict:
    d = yaml.safe_load(path.read_text())
    d.pop("output", None)
    d["sequence"] = str(Path(d["sequence"]).resolve())  # the same data reached through a link is the same
    return d


def compare(ref: Path, new: Path) -> int:
    bad = 0
    runs = sorted(p.name for p in (ref / "runs").iterdir() if p.is_dir())
    for name in runs:
        for f in FILES:
            a, b = ref / "runs" / name / f, new / "runs" / name / f
            if not b.is_file():
                print(f"{name}/{f}: missing in {new}")
                bad += 1
                continue
            if f == "summary.json":
                sa, sb = _summary(a), _summary(b)
                same = sa == sb
                if not same:
                    keys = sorted(k for k in set(sa) | set(sb) if k not in sa or k not in sb or sa[k] != sb[k])
                    print(f"{name}/{f}: keys differ: {', '.join(keys)}")
            elif f == "stats.csv":
                same = _stats(a) == _stats(b)
            elif f == "config_resolved.yaml":
                same = _config(a) == _config(b)
            else:
                same = a.read_bytes() == b.read_bytes()
            if not same:
                print(f"{name}/{f}: DIFFERS")
                bad += 1
    print(f"{len(runs)} runs x {len(FILES)} files compared: {bad} differ")
    return 1 if bad else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--cache", type=Path, default=Path("windowvo_output/bench_cache"))
    r.add_argument("--duration", type=float, default=30.0)
    c = sub.add_parser("compare")
    c.add_argument("ref", type=Path)
    c.add_argument("new", type=Path)
    a = p.parse_args()
    if a.cmd == "run":
        run(a.out, a.cache, a.duration)
        return 0
    return compare(a.ref, a.new)


if __name__ == "__main__":
    sys.exit(main())
