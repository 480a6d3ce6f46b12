"""``python -m windowvo.bench --suite stages``: the per-stage CPU budget of a whole run.

Each case is one job in a fresh interpreter, sequential run mode (so each stage's CPU is its own), the
Rerun recording on (``viz.rerun=save``), with the stage timers of ``runtime/stage_timer.py`` started
around it: a rendered 640x480 loop and a KITTI-size sequence (the KITTI excerpt 06 from ``../shared/data``
with synthetic wheels, or, without it, a rendered 1226x370 street). Every number is thread CPU time
(``time.thread_time``), not wall time, so a busy machine slows it much less than it slows the wall clock.
The start-up (a fresh ``python -c "import windowvo.runtime.job"``, and with the recording's import) is
measured separately, as the CPU time of a child process; the whole process's CPU (start-up, job, every
thread) is reported beside the job's.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..runtime.stage_timer import STAGE_SCOPE, Scope, Stage, StageTimes
from .bench import SHARED_DATA, CaseKind, SeqCase, case_config_data

if TYPE_CHECKING:  # pragma: no cover
    from ..config import Config

KITTI_EXCERPT = "kitti06_000-050"
LOOP_DURATION_S = 15.0
# The 640x480 case; the KITTI-size fallback when the excerpt is absent (a street at KITTI's resolution).
LOOP_CASE = SeqCase("stages_loop_640x480", CaseKind.SYNTH,
                    spec={"duration_s": LOOP_DURATION_S, "seed": 31})
STREET_SIZE = {"width": 1226, "height": 370, "fx": 707.0}
# What the start-up measures: the run's imports, and those with the recording's (rerun).
STARTUP_IMPORTS = {"python": "pass", "windowvo.runtime.job": "import windowvo.runtime.job",
                   "windowvo.runtime.job + rerun logger": "import windowvo.runtime.job, windowvo.viz.rerun_logger"}
UNTIMED = "rest of the frame, not timed (journal, wheel buffer, stats record)"


def kitti_size_case() -> SeqCase:
    """The KITTI excerpt (synthetic wheels, +1%) when present, else a rendered 1226x370 street."""
    if (SHARED_DATA / KITTI_EXCERPT).is_dir():
        return SeqCase(f"stages_{KITTI_EXCERPT}", CaseKind.KITTI, path=SHARED_DATA / KITTI_EXCERPT)
    from ..synth.generate import scene_defaults
    from ..synth.scenes import SceneKind

    spec = {**scene_defaults(SceneKind.STREET), "scene": SceneKind.STREET, **STREET_SIZE, "duration_s": 8.0,
            "seed": 52}
    return SeqCase("stages_street_1226x370", CaseKind.SYNTH, spec=spec)


def _stats(values: list[float]) -> dict:
    a = np.asarray(values, float)
    return {"mean": float(a.mean()) if a.size else float("nan"),
            "median": float(np.median(a)) if a.size else float("nan"), "n": int(a.size)}


def frame_rows(times: StageTimes) -> list[dict]:
    """A row per stage timed in the frames (ms per frame over every frame; back-end stages also per keyframe),
    one for the recording's logging thread (per logged item), and the rest of the frame nobody times."""
    frames = times.frames
    kfs = [f for f in frames if f.keyframe]
    rows = []
    for stage in Stage:
        if STAGE_SCOPE[stage] is Scope.RUN or stage is Stage.RECORDING_THREAD:
            continue
        per_frame = [f.ms.get(stage, 0.0) for f in frames]
        row = {"stage": stage.value, "scope": STAGE_SCOPE[stage].value, "per_frame": _stats(per_frame),
               "total_ms": float(sum(per_frame))}
        if STAGE_SCOPE[stage] is Scope.KEYFRAME:
            row["per_keyframe"] = _stats([f.ms.get(stage, 0.0) for f in kfs])
        rows.append(row)
    rows.append({"stage": UNTIMED, "scope": Scope.FRAME.value,
                 "per_frame": _stats([f.total_ms - f.stages_ms for f in frames]),
                 "total_ms": float(sum(f.total_ms - f.stages_ms for f in frames))})
    logged = times.other_threads_ms.get(Stage.RECORDING_THREAD, [])
    if logged:
        rows.append({"stage": Stage.RECORDING_THREAD.value + "; per logged item: one a frame, one at the end",
                     "scope": "other thread", "per_frame": _stats(logged), "total_ms": float(sum(logged))})
    return rows


def run_rows(times: StageTimes) -> list[dict]:
    """The run's thread before the first frame and after the last: the stages timed there and the rest."""
    rows = []
    for label, total, stages in (("before the first frame", times.before_frames_ms, times.before_stages_ms),
                                 ("after the last frame", times.after_frames_ms, times.after_stages_ms)):
        for stage, ms in stages.items():
            rows.append({"stage": f"{label}: {stage.value}", "scope": Scope.RUN.value, "total_ms": ms})
        rest = "loading the sequence, building the pipeline (first-use imports included)" if label.startswith("before") else \
            "trajectory assembly, evaluation, journal"
        rows.append({"stage": f"{label}: {rest}", "scope": Scope.RUN.value,
                     "total_ms": total - float(sum(stages.values()))})
    return rows


def measure_job(cfg: Config, name: str = "") -> dict:
    """A job with the stage timers on: the stage rows, the frame totals, and the CPU of the job's thread, of all
    its threads and of the whole process so far (start-up included when this is a fresh interpreter)."""
    from ..cli.hidden_modules import pandas_hidden
    from ..runtime import stage_timer
    from ..runtime.job import run_job

    cpu0, wall0 = time.process_time(), time.perf_counter()
    with pandas_hidden(), stage_timer.recording() as rec:  # as ``python -m windowvo.run`` runs it
        rep = run_job(cfg)
        times = rec.times()
    job_cpu_s, job_wall_s = time.process_time() - cpu0, time.perf_counter() - wall0
    res = budget(times, name or cfg.sequence.name, f"{rep.sequence.camera.width}x{rep.sequence.camera.height}")
    # The process's other threads, which time nothing (rerun's own encoding and writing, OpenCV's workers).
    res["untimed_threads_ms"] = max(0.0, 1000.0 * job_cpu_s - res["run_thread_ms"] - res["other_threads_timed_ms"])
    return {**res, "job_cpu_s": job_cpu_s, "job_wall_s": job_wall_s, "process_cpu_s": time.process_time()}


def budget(times: StageTimes, name: str, size: str) -> dict:
    """A run's stage times as the table's rows and totals."""
    return {"case": name, "size": size, "frames": len(times.frames),
            "keyframes": sum(f.keyframe for f in times.frames), "frame_rows": frame_rows(times),
            "run_rows": run_rows(times),
            "frame_total": _stats([f.total_ms for f in times.frames]),
            "keyframe_total": _stats([f.total_ms for f in times.frames if f.keyframe]),
            "run_thread_ms": times.total_ms,
            "other_threads_timed_ms": float(sum(sum(v) for v in times.other_threads_ms.values()))}


def budget_job(case: SeqCase, cache: str, out_root: str, overrides: tuple[str, ...] = ()) -> dict:
    """One case's job (sequential, recording on, ``overrides`` as ``--set KEY=VALUE``) with the stage timers on;
    runs in a fresh interpreter."""
    import logging

    logging.basicConfig(level=logging.ERROR)
    from ..config import config_from_dict

    data = case_config_data(case, Path(cache), Path(out_root), rerun=True, overrides=overrides)
    data["run_mode"] = "sequential"  # each stage's CPU is its own (an override cannot change it)
    return measure_job(config_from_dict(data), case.name)


def startup_cpu(repeats: int = 3) -> dict:
    """CPU seconds (user + system) of a fresh interpreter running each of ``STARTUP_IMPORTS``; the least of
    ``repeats`` (page cache warm after the first)."""
    out = {}
    for name, code in STARTUP_IMPORTS.items():
        runs = []
        for _ in range(repeats):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run([sys.executable, "-c", code], check=True)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            runs.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
        out[name] = min(runs)
    return out


def bench_stages(cache: Path, out_root: Path, overrides: tuple[str, ...] = ()) -> dict:
    """The 640x480 and the KITTI-size case, each in a fresh interpreter (``overrides``: ``--set KEY=VALUE`` for
    both), and the start-up."""
    from .bench import ensure_rendered
    from .executors import values_in_processes

    cases = [LOOP_CASE, kitti_size_case()]
    for c in cases:
        if c.kind is CaseKind.SYNTH:
            ensure_rendered(c, cache)
    rows = values_in_processes([(c.name, budget_job, (c, str(cache), str(out_root / "stages"), tuple(overrides)))
                                for c in cases], 1, "bench stages")
    res = {"cases": rows, "startup_cpu_s": startup_cpu(), "overrides": list(overrides)}
    (out_root / "stages").mkdir(parents=True, exist_ok=True)
    (out_root / "stages" / "stages.json").write_text(json.dumps(res, indent=2))
    return res


def _ms(v: float | None) -> str:
    return "" if v is None or not np.isfinite(v) else f"{v:.2f}"


def case_table(r: dict) -> str:
    """One case's markdown table: stage | ms per frame (mean, median) | ms per keyframe | share of the total (the
    job's CPU, every thread: the run's, the recording's logging thread and, when measured, the untimed ones)."""
    untimed = r.get("untimed_threads_ms")
    total = r["run_thread_ms"] + r["other_threads_timed_ms"] + (untimed or 0.0)
    lines = ["| stage | ms per frame (mean / median) | ms per keyframe (mean / median) | share of the total |",
             "|---|---|---|---|"]
    for row in r["frame_rows"]:
        pf, pk = row["per_frame"], row.get("per_keyframe")
        kf = f"{_ms(pk['mean'])} / {_ms(pk['median'])}" if pk else ""
        lines.append(f"| {row['stage']} | {_ms(pf['mean'])} / {_ms(pf['median'])} | {kf} | "
                     f"{100.0 * row['total_ms'] / total:.1f}% |")
    ft, kt = r["frame_total"], r["keyframe_total"]
    lines.append(f"| **frame total (run's thread)** | {_ms(ft['mean'])} / {_ms(ft['median'])} | "
                 f"{_ms(kt['mean'])} / {_ms(kt['median'])} | |")
    for row in r["run_rows"]:
        lines.append(f"| {row['stage']} (once, ms) | {_ms(row['total_ms'])} | | {100.0 * row['total_ms'] / total:.1f}% |")
    if untimed is not None:
        lines.append(f"| other threads, not timed (rerun's own, OpenCV's; whole job, ms) | {_ms(untimed)} | | "
                     f"{100.0 * untimed / total:.1f}% |")
    return "\n".join(lines)


def stages_text(res: dict) -> str:
    """Every case's table, its totals, and the start-up."""
    parts = []
    for r in res["cases"]:
        parts.append(f"### {r['case']} ({r['size']}, {r['frames']} frames, {r['keyframes']} keyframes)\n")
        parts.append(case_table(r) + "\n")
        parts.append(f"Total: the run's thread {r['run_thread_ms'] / 1000:.2f} s CPU, the recording's logging "
                     f"thread {r['other_threads_timed_ms'] / 1000:.2f} s; the job, every thread (the shares' base) "
                     f"{r['job_cpu_s']:.2f} s CPU in {r['job_wall_s']:.2f} s wall; the whole process, start-up "
                     f"included, {r['process_cpu_s']:.2f} s CPU.\n")
    s = res["startup_cpu_s"]
    parts.append("Start-up (a fresh interpreter, CPU s, least of 3): " +
                 ", ".join(f"`{k}` {v:.2f}" for k, v in s.items()) + "\n")
    return "\n".join(parts)
