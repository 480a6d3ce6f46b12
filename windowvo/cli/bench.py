"""Command line: ``python -m windowvo.bench`` (see :mod:`windowvo.tools.bench`)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from ..config import apply_overrides, config_from_dict
from ..errors import WindowVOError, cli_error
from ..tools import bench as _tools_bench
from ..tools.bench import (
    CaseKind,
    bench_backend,
    bench_bag,
    bench_frontend,
    bench_memory,
    bench_modes,
    bench_rerun,
    ensure_rendered,
    kitti_cases,
    run_cases_in_processes,
    sequences_caption,
    sequences_table,
    synthetic_cases,
)
from ..tools.helptext import first_line, plain_help
from ..tools.scale_suite import SEED_KEY


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m windowvo.bench", description=first_line(_tools_bench.__doc__),
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=plain_help("\n".join((_tools_bench.__doc__ or "").splitlines()[1:])))
    p.add_argument("--suite", nargs="+", default=["sequences"], choices=["sequences", "frontend", "backend", "rerun", "memory", "bag", "modes", "scale", "stages", "speed"],
                   help="scale: the scale suite (fused cues against each cue alone, windowvo/tools/scale_suite.py); "
                        "stages: the per-stage CPU budget (windowvo/tools/stage_budget.py); speed: whole processes "
                        "against the chaining baseline, back to back (windowvo/tools/speed.py)")
    p.add_argument("--out", default="windowvo_output/bench", help="outputs, JSON and plots")
    p.add_argument("--cache", default="windowvo_output/bench_cache", help="rendered sequences (reused)")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of each synthetic sequence")
    p.add_argument("--jobs", type=int, default=1, help="sequences run in parallel processes")
    p.add_argument("--only", nargs="*", help="run only these sequence names (of the sequences, scale and speed "
                   "suites; a name none of the selected suites holds is an error)")
    p.add_argument("--backend-keyframes", type=int, default=5000)
    p.add_argument("--repeats", type=int, default=3, help="speed: alternated pairs of whole processes per sequence "
                   "(the fastest of each counts)")
    p.add_argument("--seeds", type=int, default=1, help="scale: run the ways that use the floor (fused, floor only) "
                   "with this many seeds of the floor plane's RANSAC (backend.ground.seed 0..N-1) and compare each "
                   "way's median: one run's ATE moves by chance, the floor only's by over 10%% on half the sequences")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every windowvo run of the sequences, scale and stages suites (repeatable; "
                        "the scale suite's cue switches of each way still apply), "
                        "e.g. --set backend.marginalize_every=1")
    return p


def _sequences(a, out: Path, cache: Path) -> list[dict]:
    cases = synthetic_cases(a.duration) + kitti_cases()
    if a.only:
        cases = [c for c in cases if c.name in a.only]
    # Render first, in this process, so that each run's peak RSS is the pipeline's own.
    for c in cases:
        if c.kind is CaseKind.SYNTH:
            ensure_rendered(c, cache)
    if a.set:
        print(f"config overrides for every run: {' '.join(a.set)}\n")
    rows = run_cases_in_processes(cases, cache, out, a.jobs, tuple(a.set))
    print("## Sequences\n")
    print(sequences_caption(rows) + "\n")
    print(sequences_table(rows))
    print()
    return rows


def _frontend(cache: Path) -> dict:
    fe = bench_frontend(cache)
    print("## Front end (640x480)\n\n| tracker | frames | mean ms | median ms | p95 ms | fps |\n|---|---|---|---|---|---|")
    for k, v in fe.items():
        print(f"| {k} | {v['frames']} | {v['mean_ms']:.2f} | {v['median_ms']:.2f} | {v['p95_ms']:.2f} | {v['fps']:.0f} |")
    print()
    return fe


def _backend(n_keyframes: int) -> dict:
    with ProcessPoolExecutor(max_workers=1) as ex:
        be = ex.submit(bench_backend, n_keyframes).result()
    print("## Back end (feature-level, window 20)\n")
    print("| keyframes | landmarks (median) | obs/kf | median ms | p95 ms | RSS MB after N keyframes |\n|---|---|---|---|---|---|")
    rss = ", ".join(f"{k}: {v:.0f}" for k, v in be["rss_mb_after"].items())
    print(f"| {be['keyframes']} | {be['landmarks_median']:.0f} | {be['observations_per_keyframe']:.0f} | "
          f"{be['median_ms']:.1f} | {be['p95_ms']:.1f} | {rss} |\n")
    return be


def _rerun(cache: Path, out: Path) -> dict:
    rr_res = bench_rerun(cache, out)
    on = rr_res["on"]
    print(f"## Rerun recording cost (image on every {on['image_every']} frame(s), JPEG quality "
          f"{on['jpeg_quality']})\n\n| recording | frames | job wall s | pipeline s | CPU s | recording MB |"
          "\n|---|---|---|---|---|---|")
    for k in ("off", "on"):
        r = rr_res[k]
        print(f"| {k} | {r['frames']} | {r['wall_s']:.2f} | {r['pipeline_s']:.2f} | {r['cpu_s']:.2f} | "
              f"{r.get('size_mb', 0.0):.1f} |")
    print(f"\nwall-time overhead {rr_res['overhead_pct']:.1f}%, CPU overhead {rr_res['cpu_overhead_pct']:.1f}%, "
          f"logger time in the run's thread {rr_res['viewer_busy_pct']:.1f}% of the job, "
          f"{rr_res['kb_per_frame']:.0f} kB per frame\n")
    return rr_res


def _modes(cache: Path, out: Path) -> dict:
    md = bench_modes(cache, out)
    print("## Run modes (30 s loop, default config; fastest of 3 fresh processes each)\n\n"
          "| Rerun recording | sequential fps | pipelined fps | speed-up | back-end ms/kf median (seq / pip) | "
          "cores busy (seq / pip) | identical trajectories | E-matrix chaining fps |\n"
          "|---|---|---|---|---|---|---|---|")
    for rerun in ("save", "off"):
        r = md[rerun]
        seq_r, pip_r = r["sequential"], r["pipelined"]
        print(f"| {rerun} | {seq_r['fps']:.1f} | {pip_r['fps']:.1f} | {r['speedup']:.2f}x | "
              f"{seq_r['backend_ms_median']:.1f} / {pip_r['backend_ms_median']:.1f} | "
              f"{seq_r['cores_busy']:.2f} / {pip_r['cores_busy']:.2f} | "
              f"{'yes' if r['identical'] else 'NO'} | {md['chaining_fps']:.1f} |")
    print(f"\ncores busy: CPU time of all threads and of the back-end process over a whole job, divided by its "
          f"wall time ({os.cpu_count()} cores here). Doing the same CPU work, a job that keeps c cores busy in "
          f"sequential mode can run at most {os.cpu_count()}/c times faster on these cores.\n")
    return md


def _memory(cache: Path, out: Path) -> dict:
    mem = bench_memory(cache, out)
    print("## Whole-run memory\n\n| frames | keyframes | fps | peak RSS MB |\n|---|---|---|---|")
    for v in mem.values():
        if isinstance(v, dict):
            print(f"| {v['frames']} | {v['keyframes']} | {v['fps']:.1f} | {v['peak_rss_mb']:.0f} |")
    print(f"\ngrowth from 500 frames to the long run: {mem['growth_pct']:.1f}%\n")
    return mem


def _scale(a, out: Path, cache: Path) -> dict:
    from ..tools import scale_suite

    cases = scale_suite.suite_cases()
    if a.only:
        cases = [c for c in cases if c.name in a.only]
    rows = scale_suite.run_suite(cases, cache / "scale", out / "scale", a.jobs, tuple(a.set), a.seeds)
    s = scale_suite.write_results(rows, out / "scale")
    print("## Scale suite: fused cues against each cue alone (ATE m)\n")
    print(scale_suite.table(rows) + "\n")
    print(scale_suite.summary_text(s) + "\n")
    return {"rows": rows, "summary": s}


def _stages(a, cache: Path, out: Path) -> dict:
    from ..tools import stage_budget

    res = stage_budget.bench_stages(cache, out, tuple(a.set))
    print("## Per-stage CPU budget (thread CPU time, sequential mode, recording on)\n")
    print(stage_budget.stages_text(res))
    return res


def _speed(a, cache: Path, out: Path) -> dict:
    from ..tools import speed

    return speed.bench_speed(cache, out, a.repeats, a.only)


def _bag(cache: Path, out: Path) -> dict:
    bag_res = bench_bag(cache, out)
    print("## ROS bag input (frames streamed)\n\n| bag | MB | frames | keyframes | fps | peak RSS MB |\n"
          "|---|---|---|---|---|---|")
    for k, v in bag_res.items():
        if isinstance(v, dict):
            print(f"| {k} | {v['bag_mb']:.0f} | {v['frames']} | {v['keyframes']} | {v['fps']:.1f} | "
                  f"{v['peak_rss_mb']:.0f} |")
    print(f"\npeak RSS growth from the small bag to the large one: {bag_res['growth_pct']:.1f}%\n")
    return bag_res


# The suites whose sequences --only selects, and their sequence names.
ONLY_SUITES = ("sequences", "scale", "speed")


def _names(suite: str, duration: float) -> list[str]:
    from ..tools import scale_suite, speed

    if suite == "sequences":
        return [c.name for c in synthetic_cases(duration) + kitti_cases()]
    if suite == "scale":
        return [c.name for c in scale_suite.suite_cases()]
    return [c.name for c in speed.speed_cases()]


def unknown_only(a) -> str | None:
    """``--only`` names that no selected suite holds (a typo would run nothing): the error's text, else None."""
    if not a.only:
        return None
    suites = [s for s in a.suite if s in ONLY_SUITES]
    if not suites:
        return f"--only selects sequences of the {', '.join(ONLY_SUITES)} suites; none of them is selected"
    known = {n for s in suites for n in _names(s, a.duration)}
    missing = [n for n in a.only if n not in known]
    if missing:
        return (f"--only: no sequence named {', '.join(missing)} in the {', '.join(suites)} suite(s) "
                f"(known: {', '.join(sorted(known))})")
    return None


KITTI_SUITES = ("sequences", "scale", "speed", "stages")


def missing_kitti_note(suites: list[str]) -> str | None:
    """A note when selected suites have KITTI rows and the excerpts are not beside the repository (they are
    left out then, not failed): a suite run from another checkout (a git worktree) would otherwise count fewer rows
    without a word."""
    if not any(s in KITTI_SUITES for s in suites):
        return None
    missing = [n for n in _tools_bench.KITTI_EXCERPTS if not (_tools_bench.SHARED_DATA / n).is_dir()]
    if not missing:
        return None
    return (f"the KITTI excerpts {', '.join(missing)} are not in {_tools_bench.SHARED_DATA} (../shared/data beside "
            f"the repository): their rows are left out")


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    out, cache = Path(a.out), Path(a.cache)
    if a.repeats < 1:
        print(f"windowvo.bench: error: --repeats must be at least 1 (got {a.repeats})", file=sys.stderr)
        return 2
    bad_only = unknown_only(a)
    if bad_only:
        print(f"windowvo.bench: error: {bad_only}", file=sys.stderr)
        return 2
    if a.seeds < 1:
        print(f"windowvo.bench: error: --seeds must be at least 1 (got {a.seeds})", file=sys.stderr)
        return 2
    if a.seeds > 1 and "scale" not in a.suite:
        print("windowvo.bench: error: --seeds is for the scale suite (--suite scale)", file=sys.stderr)
        return 2
    if a.seeds > 1 and any(kv.split("=", 1)[0].strip() == SEED_KEY for kv in a.set):
        print(f"windowvo.bench: error: --seeds sets {SEED_KEY} itself: not also with --set", file=sys.stderr)
        return 2
    if a.set:  # a bad key or value is one line and exit 2, before anything is rendered or run
        try:
            config_from_dict(apply_overrides({"sequence": ".", "output": str(out), "progress": False}, list(a.set)))
        except WindowVOError as err:
            return cli_error(err, "windowvo.bench")
    note = missing_kitti_note(a.suite)
    if note:
        print(f"windowvo.bench: note: {note}", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    suites = {"sequences": lambda: _sequences(a, out, cache), "frontend": lambda: _frontend(cache),
              "backend": lambda: _backend(a.backend_keyframes), "rerun": lambda: _rerun(cache, out),
              "modes": lambda: _modes(cache, out), "memory": lambda: _memory(cache, out), "bag": lambda: _bag(cache, out),
              "scale": lambda: _scale(a, out, cache), "stages": lambda: _stages(a, cache, out),
              "speed": lambda: _speed(a, cache, out)}
    try:
        results: dict = {name: run() for name, run in suites.items() if name in a.suite}
    except WindowVOError as err:  # a run of a suite failed (e.g. a child process of the speed suite): one line
        return cli_error(err, "windowvo.bench")
    (out / "bench.json").write_text(json.dumps(results, indent=2, default=float))
    print(f"results: {out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
