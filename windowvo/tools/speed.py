"""Whole-process speed against the chaining baseline (issue #30): ``python -m windowvo.bench --suite speed``.

Each sequence is run as a user runs it, in a fresh interpreter each time, back to back and alternated:
windowvo (``python -m windowvo.run CONFIG``, the default configuration and run mode, the Rerun recording saved)
and the frame-to-frame chaining baseline (``eval.baselines.essential_chaining`` with ORB 2000: the same sequence
loaded through the same config, then ORB, ratio test, essential matrix by RANSAC, recoverPose, scaled by the
wheel distance; its trajectory written and evaluated). Start-up (imports, loading) counts for both. The
fastest of ``repeats`` counts for each (the others are slowed by whatever else runs on the machine); both
wall time and CPU time (user + system of the process and its children) are reported, and each method's ATE.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import yaml

from ..errors import WindowVOError
from .bench import CaseKind, SeqCase, case_config_data, children_cpu_s, kitti_cases, synthetic_cases

CHAINING_FEATURES = 2000  # the baseline: ORB 2000
SPEED_DURATION_S = 30.0  # the rendered loop of the issue: 600 frames at 20 fps
# KITTI-size frames as long as the KITTI sequence (160 frames at 10 Hz): the 51-frame excerpts are mostly
# start-up, so a rendered street at KITTI's resolution and field of view measures the per-frame work at that size.
KITTI_SIZE_STREET = SeqCase("street_1226x370", CaseKind.SYNTH,
                            spec={"scene": "street", "width": 1226, "height": 370, "fx": 707.0, "duration_s": 16.0,
                                  "seed": 53})


@dataclass
class ProcessTime:
    """One whole process: wall seconds, CPU seconds (with its children), and the ATE it reached."""

    wall_s: float
    cpu_s: float
    ate_se3_m: float


@dataclass
class SpeedRow:
    sequence: str
    frames: int
    windowvo: ProcessTime  # the fastest of the repeats
    chaining: ProcessTime
    repeats: int
    # chaining / windowvo wall time of each pair run back to back: the machine's drift during the suite cancels
    pair_ratios: list[float] = field(default_factory=list)

    @property
    def ratio(self) -> float:
        """How many times faster windowvo's whole process is than the chaining baseline's (wall time)."""
        return self.chaining.wall_s / self.windowvo.wall_s

    @property
    def pair_ratio_median(self) -> float:
        """The median of the pairs' ratios (nan without pairs)."""
        return statistics.median(self.pair_ratios) if self.pair_ratios else float("nan")


def speed_cases() -> list[SeqCase]:
    """The rendered 640x480 loop and figure eight of the benchmark (30 s at 20 fps), a rendered street at KITTI's
    size (161 frames at 10 Hz, the scene's default wheels) and the KITTI excerpts with synthetic wheels (+1%), when
    ``../shared/data`` is there."""
    rendered = [c for c in synthetic_cases(SPEED_DURATION_S) if c.name in ("loop", "figure_eight_vibration")]
    kitti = [c for c in kitti_cases() if c.kind is CaseKind.KITTI and c.name.endswith("000-050")]
    return [*rendered, street_case(), *kitti]


def street_case() -> SeqCase:
    """The KITTI-size street with the street scene's defaults (camera 1.65 m, 10 Hz, road speed, kerbs, cars)."""
    from ..synth.generate import scene_defaults
    from ..synth.scenes import SceneKind

    spec = {**scene_defaults(SceneKind.STREET), **(KITTI_SIZE_STREET.spec or {}), "scene": SceneKind.STREET}
    return SeqCase(KITTI_SIZE_STREET.name, CaseKind.SYNTH, spec=spec)


def _timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """Wall and CPU seconds of one child process (and its own children), which must succeed."""
    cpu0, t0 = children_cpu_s(), time.perf_counter()
    done = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=1800)
    wall, cpu = time.perf_counter() - t0, children_cpu_s() - cpu0
    if done.returncode != 0:
        tail = done.stderr.strip().splitlines()[-1:] or ["(no output)"]
        raise WindowVOError(f"speed suite: {' '.join(cmd[1:4])} failed (exit {done.returncode}): {tail[0]}")
    return wall, cpu


def chaining_job(config_path: str, out: str) -> None:
    """The chaining baseline as a whole process: load the config's sequence, chain, evaluate, write ATE JSON."""
    from ..config import load_config
    from ..eval.baselines import essential_chaining
    from ..eval.metrics import evaluate
    from ..runtime.job import load_sequence

    seq = load_sequence(load_config(config_path))
    run = essential_chaining(seq, n_features=CHAINING_FEATURES)
    acc = evaluate(seq.groundtruth, run.trajectory) if seq.groundtruth is not None else None
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / "chaining.json").write_text(json.dumps(
        {"frames": run.n_frames, "ate_se3_m": acc.ate_se3_rmse_m if acc is not None else float("nan")}))


def _windowvo_once(case: SeqCase, cache: Path, out: Path, k: int, env: dict[str, str]) -> tuple[ProcessTime, dict]:
    data = case_config_data(case, cache, out / f"windowvo_{k}", rerun=True)
    data.pop("run_mode", None)  # the default run mode, as a user runs it
    data["output"] = str(out / f"windowvo_{k}")
    cfg = out / f"windowvo_{k}.yaml"
    cfg.write_text(yaml.safe_dump(data))
    wall, cpu = _timed([sys.executable, "-m", "windowvo.run", str(cfg)], env)
    summary = json.loads((out / f"windowvo_{k}" / "summary.json").read_text())
    ate = (summary.get("accuracy") or {}).get("ate_se3_rmse_m")
    return ProcessTime(wall, cpu, float("nan") if ate is None else float(ate)), summary


def _chaining_once(case: SeqCase, cache: Path, out: Path, k: int, env: dict[str, str]) -> tuple[ProcessTime, int]:
    data = case_config_data(case, cache, out / f"chaining_{k}")
    cfg = out / f"chaining_{k}.yaml"
    cfg.write_text(yaml.safe_dump(data))
    code = f"from windowvo.tools.speed import chaining_job; chaining_job({str(cfg)!r}, {str(out / f'chaining_{k}')!r})"
    wall, cpu = _timed([sys.executable, "-c", code], env)
    res = json.loads((out / f"chaining_{k}" / "chaining.json").read_text())
    return ProcessTime(wall, cpu, float(res["ate_se3_m"])), int(res["frames"])


def run_speed_case(case: SeqCase, cache: Path, out: Path, repeats: int = 3) -> SpeedRow:
    """``repeats`` alternated pairs of whole processes; the fastest of each method counts."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    ours: list[ProcessTime] = []
    theirs: list[ProcessTime] = []
    summary: dict = {}
    frames = 0
    for k in range(repeats):
        t, summary = _windowvo_once(case, cache, out, k, env)
        ours.append(t)
        c, frames = _chaining_once(case, cache, out, k, env)
        theirs.append(c)
    return SpeedRow(case.name, int(summary.get("frames", frames)), min(ours, key=lambda p: p.wall_s),
                    min(theirs, key=lambda p: p.wall_s), repeats,
                    [c.wall_s / t.wall_s for t, c in zip(ours, theirs, strict=True)])


def speed_table(rows: list[SpeedRow]) -> str:
    head = ("| sequence | frames | windowvo whole process s (fps) / CPU s | chaining (ORB 2000) s (fps) / CPU s "
            "| windowvo faster by (wall, fastest of each) | pairs: median (min-max) | ATE SE(3) m windowvo / chaining |"
            "\n|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        w, c = r.windowvo, r.chaining
        lines.append(f"| {r.sequence} | {r.frames} | {w.wall_s:.1f} ({r.frames / w.wall_s:.1f}) / {w.cpu_s:.1f} "
                     f"| {c.wall_s:.1f} ({r.frames / c.wall_s:.1f}) / {c.cpu_s:.1f} | **{r.ratio:.2f}x** "
                     f"| {_pairs(r)} | {w.ate_se3_m:.3f} / {c.ate_se3_m:.3f} |")
    return "\n".join(lines)


def _pairs(r: SpeedRow) -> str:
    if not r.pair_ratios:
        return "-"
    return f"{r.pair_ratio_median:.2f}x ({min(r.pair_ratios):.2f}-{max(r.pair_ratios):.2f})"


def bench_speed(cache: Path, out: Path, repeats: int = 3, only: list[str] | None = None) -> dict:
    """Every speed case (``only``: those of these names), one after the other (never in parallel: they are timed).
    The folders are made absolute: each process reads a config file written under ``out``, whose relative paths
    would be taken from there."""
    if repeats < 1:
        raise ValueError(f"--repeats must be at least 1 (got {repeats})")
    cache, out = cache.resolve(), out.resolve()
    cases = [c for c in speed_cases() if not only or c.name in only]
    rows = [run_speed_case(c, cache, out / "speed" / c.name, repeats) for c in cases]
    print("## Whole-process speed against frame-to-frame chaining (issue #30)\n")
    print(speed_table(rows) + "\n")
    return {"rows": [{**asdict(r), "ratio": r.ratio, "pair_ratio_median": r.pair_ratio_median} for r in rows]}
