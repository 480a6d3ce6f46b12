"""``python -m windowvo.batch SPEC.yaml``: evaluate many recordings x many configs, locally or on Ray.

A spec (YAML, paths relative to it) names the sequences, a base config, a grid of overrides
(runs are the Cartesian product), an output root and an optional per-run time-out::

    sequences:
      - path: recordings/*           # a folder or a glob (of folders; also files for rosbag/video)
        dataset: native
      - path: kitti/sequences/06
        dataset: kitti
        name: kitti06                # optional (single folders only)
        overrides: {odometry_synthesis: {enabled: true}, max_frames: 300}
    base: base.yaml                  # a config file, or an inline mapping
    grid:
      frontend.max_features: [150, 200]
      backend.window_keyframes: [10, 20]
    output: batch_out
    timeout_s: 600                   # per run (optional)
    rerun: off                       # viz.rerun for every run (default off)

Each run is ``python -m windowvo.run RUN_DIR/job.yaml --no-progress -q`` in its own process, so
a crash, a bad sequence or a time-out fails that run only (status ``failed`` and a one-line
reason). A run whose folder holds a summary for the same resolved config (hash in
``batch_run.json``) is reused unless ``--force``. Outputs in the output root: ``results.csv``,
``report.md``, ``ate_per_config.png``, ``batch.json``, and ``runs/CONFIG/SEQUENCE/`` per run.
"""

from __future__ import annotations

import copy
import csv
import glob
import hashlib
import itertools
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..config import ConfigError, DatasetKind, RerunMode, config_from_dict, read_yaml_mapping, validation_problems
from .executors import ExecutorKind, Task, TaskOutcome, TaskStatus, make_executor
from .kitti_columns import KITTI_COLUMNS, flat_values, kitti_errors, shown_columns

RUN_MARKER = "batch_run.json"
JOB_CONFIG = "job.yaml"
RESERVED_GRID_KEYS = ("sequence", "output")
_GLOB_CHARS = set("*?[")
FILE_DATASETS = ("rosbag", "video")  # dataset kinds whose sequence may be a file (a glob matches files too)


# ---------------------------------------------------------------------------- the spec


class _SpecModel(BaseModel):
    model_config = ConfigDict(extra="forbid")


class SequenceEntry(_SpecModel):
    path: str = Field(min_length=1)
    dataset: DatasetKind = DatasetKind.NATIVE
    name: str | None = Field(None, min_length=1)  # default: the folder (or file) name
    overrides: dict[str, Any] = {}  # config keys for this sequence only (nested or dotted)


class BatchSpec(_SpecModel):
    sequences: list[SequenceEntry] = Field(min_length=1)
    base: str | dict[str, Any] = {}
    grid: dict[str, list[Any]] = {}
    output: str = Field(min_length=1)
    timeout_s: float | None = Field(None, gt=0)
    rerun: RerunMode = RerunMode.OFF

    @field_validator("sequences", mode="before")
    @classmethod
    def _bare_paths(cls, v):
        # A bare string is a native sequence folder (or glob).
        return [{"path": s} if isinstance(s, str) else s for s in v] if isinstance(v, list) else v

    @field_validator("rerun", mode="before")
    @classmethod
    def _yaml_off(cls, v):
        return "off" if v is False else v  # YAML 1.1 reads a bare `off` as false

    @model_validator(mode="after")
    def _check_grid(self) -> BatchSpec:
        for key, values in self.grid.items():
            if key.split(".")[0] in RESERVED_GRID_KEYS:
                raise ValueError(f"grid key '{key}' is set per run by the batch and cannot be varied")
            if not values:
                raise ValueError(f"grid key '{key}' has an empty list of values")
        return self


def _spec_error(path: Path, err: ValidationError) -> ConfigError:
    """Every problem of the spec, named, on one line."""
    return ConfigError(f"invalid batch spec {path}: " + "; ".join(validation_problems(err)))


def load_spec(path: Path | str) -> BatchSpec:
    path = Path(path)
    data = read_yaml_mapping(path, "batch spec")
    try:
        return BatchSpec.model_validate(data)
    except ValidationError as err:
        raise _spec_error(path, err) from None


# ---------------------------------------------------------------------------- expanding the spec into runs


def merge_config(dst: dict, src: dict) -> dict:
    """Deep-merge ``src`` into ``dst`` in place; keys may be dotted (``frontend.max_features``)."""
    for key, value in src.items():
        parts = [p for p in str(key).split(".") if p]
        if not parts:
            raise ConfigError(f"empty config key in '{key}'")
        node = dst
        for p in parts[:-1]:
            nxt = node.get(p)
            if nxt is None:
                nxt = node[p] = {}
            if not isinstance(nxt, dict):
                raise ConfigError(f"config key '{key}': '{p}' is not a section")
            node = nxt
        leaf = parts[-1]
        if isinstance(value, dict) and isinstance(node.get(leaf), dict):
            merge_config(node[leaf], value)
        else:
            node[leaf] = copy.deepcopy(value)
    return dst


def config_hash(resolved: dict) -> str:
    """Hash of a resolved config (and the windowvo version) without the per-run fields that do not change the result."""
    from .. import __version__

    core = {k: v for k, v in resolved.items() if k not in ("output", "progress")}
    core["windowvo_version"] = __version__
    return hashlib.sha256(json.dumps(core, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class ResolvedSequence:
    name: str
    path: Path
    entry: SequenceEntry


@dataclass
class RunPlan:
    run_id: str  # CONFIG/SEQUENCE
    config_id: str
    sequence: str
    dataset: DatasetKind
    grid_values: dict[str, Any]
    resolved: dict  # the full validated config (JSON types, absolute paths)
    config_hash: str
    run_dir: Path


def _resolve_sequences(spec: BatchSpec, spec_dir: Path) -> list[ResolvedSequence]:
    out: list[ResolvedSequence] = []
    for i, entry in enumerate(spec.sequences):
        raw = Path(entry.path).expanduser()
        pattern = raw if raw.is_absolute() else spec_dir / raw
        if _GLOB_CHARS & set(entry.path):
            files_ok = entry.dataset.value in FILE_DATASETS
            matches = [Path(m) for m in sorted(glob.glob(str(pattern))) if Path(m).is_dir() or files_ok]
            if not matches:
                raise ConfigError(f"batch spec: sequences[{i}]: '{entry.path}' matches no "
                                  f"{'file or folder' if files_ok else 'folder'}")
            if entry.name is not None and len(matches) > 1:
                raise ConfigError(f"batch spec: sequences[{i}]: 'name' needs a single folder, "
                                  f"'{entry.path}' matches {len(matches)}")
        else:
            matches = [pattern]  # a missing folder fails its runs, not the batch
        for m in matches:
            out.append(ResolvedSequence(entry.name or m.resolve().name, m.resolve(), entry))
    seen: dict[str, Path] = {}
    for s in out:
        if s.name in seen:
            raise ConfigError(f"batch spec: two sequences are named '{s.name}' ({seen[s.name]} and {s.path}); "
                              f"give them distinct 'name's")
        seen[s.name] = s.path
    return out


def _load_base(spec: BatchSpec, spec_dir: Path) -> dict:
    if isinstance(spec.base, dict):
        return copy.deepcopy(spec.base)
    base_path = Path(spec.base).expanduser()
    base_path = base_path if base_path.is_absolute() else spec_dir / base_path
    data = read_yaml_mapping(base_path, "base config")
    # Paths inside the base config are relative to the base config itself.
    fe = data.get("frontend")
    if isinstance(fe, dict):
        for k in ("mask", "mask_folder"):
            if isinstance(fe.get(k), str) and not Path(fe[k]).expanduser().is_absolute():
                fe[k] = str((base_path.parent / fe[k]).resolve())
    return data


def grid_combinations(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    keys = list(grid)
    return [dict(zip(keys, values)) for values in itertools.product(*(grid[k] for k in keys))]


def plan_runs(spec: BatchSpec, spec_dir: Path) -> list[RunPlan]:
    """Every sequence x grid combination, each validated as a windowvo config (bad values stop here)."""
    spec_dir = spec_dir.resolve()
    out_root = (spec_dir / Path(spec.output).expanduser()).resolve()
    base = _load_base(spec, spec_dir)
    seqs = _resolve_sequences(spec, spec_dir)
    combos = grid_combinations(spec.grid)
    width = max(2, len(str(len(combos) - 1)))
    plans: list[RunPlan] = []
    for ci, combo in enumerate(combos):
        config_id = f"c{ci:0{width}d}"
        for s in seqs:
            run_dir = out_root / "runs" / config_id / s.name
            data = copy.deepcopy(base)
            merge_config(data, {"viz": {"rerun": spec.rerun.value}, "dataset": s.entry.dataset.value})
            merge_config(data, s.entry.overrides)
            merge_config(data, combo)
            merge_config(data, {"sequence": str(s.path), "output": str(run_dir), "progress": False})
            try:
                cfg = config_from_dict(data, base_dir=spec_dir)
            except ConfigError as err:
                raise ConfigError(f"batch spec: run {config_id}/{s.name}: {err}") from None
            resolved = cfg.to_yaml_dict()
            plans.append(RunPlan(f"{config_id}/{s.name}", config_id, s.name, s.entry.dataset, combo, resolved,
                                 config_hash(resolved), run_dir))
    return plans


# ---------------------------------------------------------------------------- running


@dataclass
class RunRow:
    run_id: str
    config_id: str
    sequence: str
    dataset: str
    grid_values: dict[str, Any]
    status: TaskStatus
    reason: str = ""
    ate_se3_m: float | None = None
    ate_sim3_m: float | None = None
    ate_online_se3_m: float | None = None
    fps: float | None = None
    frames: int | None = None
    keyframes: int | None = None
    wall_s: float | None = None
    reused: bool = False
    # KITTI relative errors of the smoothed trajectory (``kitti_columns.kitti_errors``: per segment set)
    kitti: dict[str, dict] = field(default_factory=dict)
    kitti_short_t_rel_pct: float | None = None
    kitti_short_r_rel_deg_per_100m: float | None = None
    kitti_devkit_t_rel_pct: float | None = None
    kitti_devkit_r_rel_deg_per_100m: float | None = None


def _num(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else None


def row_from_summary(plan: RunPlan, summary: dict, wall_s: float | None, reused: bool,
                     kitti: dict[str, dict] | None = None) -> RunRow:
    acc = summary.get("accuracy") or {}
    online = summary.get("accuracy_online") or {}
    return RunRow(plan.run_id, plan.config_id, plan.sequence, plan.dataset.value, plan.grid_values, TaskStatus.OK,
                  "", _num(acc.get("ate_se3_rmse_m")), _num(acc.get("ate_sim3_rmse_m")),
                  _num(online.get("ate_se3_rmse_m")), _num(summary.get("fps")), summary.get("frames"),
                  summary.get("keyframes"), wall_s, reused, kitti or {}, **flat_values(kitti))


def run_kitti(plan: RunPlan, summary: dict) -> dict[str, dict]:
    """The KITTI relative errors of a finished run's smoothed trajectory (``trajectory.txt``) against the
    sequence's ground truth (loaded again here, as the run loaded it); ``{}`` without ground truth, or for a
    run up to scale whose Sim(3) scale is unknown."""
    from .. import io
    from ..errors import WindowVOError
    from ..io.trajectory import read_tum

    traj_path = plan.run_dir / "trajectory.txt"
    metric = bool(summary.get("metric", True))
    scale = None if metric else _num((summary.get("accuracy") or {}).get("sim3_scale"))
    if not traj_path.is_file() or (not metric and scale is None):
        return {}
    try:
        seq = io.load(config_from_dict(copy.deepcopy(plan.resolved)))
        try:
            gt = seq.groundtruth
        finally:
            close = getattr(seq, "close", None)
            if close is not None:
                close()
        return {} if gt is None else kitti_errors(gt, read_tum(traj_path), scale)
    except WindowVOError:
        return {}


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def finished_summary(plan: RunPlan) -> tuple[dict, dict] | None:
    """(marker, summary) when the run folder holds a finished run of exactly this config."""
    marker = _read_json(plan.run_dir / RUN_MARKER)
    if marker is None or marker.get("status") != TaskStatus.OK.value or marker.get("config_hash") != plan.config_hash:
        return None
    summary = _read_json(plan.run_dir / "summary.json")
    if summary is None or summary.get("interrupted"):
        return None
    return marker, summary


def make_task(plan: RunPlan, timeout_s: float | None) -> Task:
    """Write the run's config and return its task (stale results of an earlier run are removed first; the run
    itself moves an earlier attempt's files aside: ``--force``, since the batch decided that this run is due)."""
    plan.run_dir.mkdir(parents=True, exist_ok=True)
    for name in (RUN_MARKER, "summary.json"):
        (plan.run_dir / name).unlink(missing_ok=True)
    job = plan.run_dir / JOB_CONFIG
    job.write_text(yaml.safe_dump(plan.resolved, sort_keys=False))
    return Task(key=plan.run_id, args=("-m", "windowvo.run", str(job), "--no-progress", "-q", "--force"), timeout_s=timeout_s,
                result_json=str(plan.run_dir / "summary.json"), log_path=str(plan.run_dir / "run.log"))


def record_outcome(plan: RunPlan, outcome: TaskOutcome) -> RunRow:
    summary = outcome.value if isinstance(outcome.value, dict) else None
    if outcome.ok and summary is not None and summary.get("interrupted"):
        row = RunRow(plan.run_id, plan.config_id, plan.sequence, plan.dataset.value, plan.grid_values,
                     TaskStatus.FAILED, "interrupted", wall_s=outcome.wall_s)
    elif outcome.ok and summary is not None:
        row = row_from_summary(plan, summary, outcome.wall_s, reused=False, kitti=run_kitti(plan, summary))
    else:
        reason = outcome.reason or "no summary.json written"
        row = RunRow(plan.run_id, plan.config_id, plan.sequence, plan.dataset.value, plan.grid_values,
                     TaskStatus.FAILED, reason, wall_s=outcome.wall_s)
    marker = {"config_hash": plan.config_hash, "run_id": plan.run_id, "sequence": plan.sequence,
              "sequence_path": plan.resolved.get("sequence"), "grid": plan.grid_values, "status": row.status.value,
              "reason": row.reason, "wall_s": outcome.wall_s, "finished_unix": time.time(), "kitti": row.kitti}
    plan.run_dir.mkdir(parents=True, exist_ok=True)
    (plan.run_dir / RUN_MARKER).write_text(json.dumps(marker, indent=2, default=str))
    return row


@dataclass
class BatchResult:
    rows: list[RunRow]
    wall_s: float
    n_reused: int
    n_ran: int
    out_root: Path
    executor: str
    jobs: int
    files: dict[str, Path] = field(default_factory=dict)

    @property
    def n_failed(self) -> int:
        return sum(r.status is TaskStatus.FAILED for r in self.rows)


def run_batch(spec_path: Path | str, executor: ExecutorKind = ExecutorKind.LOCAL, jobs: int = 1,
              address: str | None = None, force: bool = False, progress: bool = True) -> BatchResult:
    spec_path = Path(spec_path)
    spec = load_spec(spec_path)
    plans = plan_runs(spec, spec_path.parent)
    out_root = (spec_path.parent.resolve() / Path(spec.output).expanduser()).resolve()
    out_root.mkdir(parents=True, exist_ok=True)
    ex = make_executor(executor, jobs, address)  # fails early (e.g. no ray) before any run starts
    t0 = time.perf_counter()
    rows: dict[str, RunRow] = {}
    todo: list[RunPlan] = []
    for plan in plans:
        done = None if force else finished_summary(plan)
        if done is not None:
            marker, summary = done
            kitti = marker["kitti"] if isinstance(marker.get("kitti"), dict) else run_kitti(plan, summary)
            rows[plan.run_id] = row_from_summary(plan, summary, _num(marker.get("wall_s")), reused=True, kitti=kitti)
        else:
            todo.append(plan)
    by_key = {p.run_id: p for p in todo}
    bar = _progress(len(plans), progress)
    try:
        if bar is not None:
            bar.update(len(rows))
        if todo:
            tasks = [make_task(p, spec.timeout_s) for p in todo]
            for outcome in ex.run(tasks):
                row = record_outcome(by_key[outcome.key], outcome)
                rows[row.run_id] = row
                if bar is not None:
                    n_failed = sum(r.status is TaskStatus.FAILED for r in rows.values())
                    bar.set_postfix(failed=n_failed, refresh=False)
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    ordered = [rows[p.run_id] for p in plans]
    result = BatchResult(ordered, time.perf_counter() - t0, len(plans) - len(todo), len(todo), out_root,
                         executor.value, jobs)
    result.files = write_reports(result, list(spec.grid), spec_path)
    return result


def _progress(total: int, enabled: bool):
    if not enabled or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="run", dynamic_ncols=True, file=sys.stderr)


# ---------------------------------------------------------------------------- reports

CSV_METRICS = ("ate_se3_m", "ate_sim3_m", "ate_online_se3_m", *(c.key for c in KITTI_COLUMNS), "fps", "frames",
               "keyframes", "wall_s")


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (list, dict)):
        return json.dumps(v)
    return str(v)


def write_results_csv(path: Path, rows: list[RunRow], grid_keys: list[str]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["run_id", "config_id", "sequence", "dataset", *grid_keys, *CSV_METRICS, "status", "reason",
                    "reused"])
        for r in rows:
            w.writerow([r.run_id, r.config_id, r.sequence, r.dataset, *(_cell(r.grid_values.get(k)) for k in grid_keys),
                        *(_cell(getattr(r, m)) for m in CSV_METRICS), r.status.value, r.reason,
                        "true" if r.reused else "false"])


def read_results_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@dataclass
class _Metric:
    attr: str
    label: str
    higher_is_better: bool = False


METRICS = (_Metric("ate_se3_m", "ATE SE(3) m"), _Metric("ate_sim3_m", "ATE Sim(3) m"),
           _Metric("ate_online_se3_m", "online ATE SE(3) m"),
           *(_Metric(c.key, c.header) for c in KITTI_COLUMNS), _Metric("fps", "fps", higher_is_better=True))


def report_metrics(rows: list[RunRow]) -> tuple[_Metric, ...]:
    """The report's metrics: the KITTI devkit (100-800 m) ones only when some run has such a segment."""
    shown = {c.key for c in shown_columns([r.kitti for r in rows])}
    return tuple(m for m in METRICS if not m.attr.startswith("kitti_") or m.attr in shown)


def _fmt(v: float | None, digits: int = 3) -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def report_markdown(result: BatchResult, grid_keys: list[str], spec_path: Path) -> str:
    rows = result.rows
    metrics = report_metrics(rows)
    configs = list(dict.fromkeys(r.config_id for r in rows))
    sequences = list(dict.fromkeys(r.sequence for r in rows))
    by_cfg = {c: [r for r in rows if r.config_id == c] for c in configs}
    n_ok = sum(r.status is TaskStatus.OK for r in rows)
    lines = [
        "# Batch report", "",
        f"Spec `{spec_path}`; executor `{result.executor}` ({result.jobs} jobs); {len(rows)} runs "
        f"({len(sequences)} sequences x {len(configs)} configs): {n_ok} ok, {result.n_failed} failed, "
        f"{result.n_reused} reused from earlier invocations; wall time {result.wall_s:.1f} s.", "",
        "## Configs", "",
        "| config | " + " | ".join(f"`{k}`" for k in grid_keys) + " |" if grid_keys else "| config |",
        "|---|" + "---|" * len(grid_keys),
    ]
    for c in configs:
        gv = by_cfg[c][0].grid_values
        lines.append(f"| {c} | " + " | ".join(_cell(gv.get(k)) for k in grid_keys) + (" |" if grid_keys else ""))
    lines += ["", "## Per config (mean and worst over the sequences that finished)", "",
              "| config | ok / runs | " + " | ".join(f"{m.label} mean | {m.label} worst" for m in metrics) + " |",
              "|---|---|" + "---|---|" * len(metrics)]
    for c in configs:
        rs = by_cfg[c]
        ok = [r for r in rs if r.status is TaskStatus.OK]
        cells = []
        for m in metrics:
            pairs = [(getattr(r, m.attr), r.sequence) for r in ok if getattr(r, m.attr) is not None]
            if not pairs:
                cells += ["", ""]
                continue
            mean = sum(v for v, _ in pairs) / len(pairs)
            worst = (min if m.higher_is_better else max)(pairs, key=lambda x: x[0])
            digits = 1 if m.higher_is_better else 3
            cells += [_fmt(mean, digits), f"{_fmt(worst[0], digits)} ({worst[1]})"]
        lines.append(f"| {c} | {len(ok)} / {len(rs)} | " + " | ".join(cells) + " |")
    # Best config per metric, compared on the sequences every config finished.
    common = [s for s in sequences if all(
        any(r.sequence == s and r.status is TaskStatus.OK for r in by_cfg[c]) for c in configs)]
    lines += ["", f"## Best config per metric (on the {len(common)} sequence(s) every config finished)", ""]
    if common:
        lines += ["| metric | best config | mean |", "|---|---|---|"]
        for m in metrics:
            means = {}
            for c in configs:
                got = [getattr(r, m.attr) for r in by_cfg[c] if r.sequence in common and r.status is TaskStatus.OK]
                if got and all(v is not None for v in got):
                    means[c] = sum(got) / len(got)
            if means:
                best = (max if m.higher_is_better else min)(means, key=lambda k: means[k])
                lines.append(f"| {m.label} | {best} | {_fmt(means[best], 1 if m.higher_is_better else 3)} |")
    else:
        lines.append("No sequence finished under every config.")
    failed = [r for r in rows if r.status is TaskStatus.FAILED]
    if failed:
        lines += ["", "## Failed runs", "", "| run | reason |", "|---|---|"]
        lines += [f"| {r.run_id} | {r.reason.replace('|', '/')} |" for r in failed]
    return "\n".join(lines) + "\n"


def plot_ate(path: Path, rows: list[RunRow]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    configs = list(dict.fromkeys(r.config_id for r in rows))
    sequences = list(dict.fromkeys(r.sequence for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True)
    x = list(range(len(configs)))
    for ax, attr, title in ((axes[0], "ate_se3_m", "ATE SE(3)"), (axes[1], "ate_sim3_m", "ATE Sim(3)")):
        for s in sequences:
            by_c = {r.config_id: getattr(r, attr) for r in rows if r.sequence == s and r.status is TaskStatus.OK}
            ys = [by_c.get(c) if by_c.get(c) is not None else float("nan") for c in configs]
            ax.plot(x, ys, marker="o", label=s)
        ax.set_title(f"{title} per config")
        ax.set_xticks(x, configs, rotation=45 if len(configs) > 8 else 0)
        ax.set_xlabel("config")
        ax.set_ylabel("RMSE (m)")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize="small", loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_reports(result: BatchResult, grid_keys: list[str], spec_path: Path) -> dict[str, Path]:
    root = result.out_root
    files = {"csv": root / "results.csv", "report": root / "report.md", "plot": root / "ate_per_config.png",
             "json": root / "batch.json"}
    write_results_csv(files["csv"], result.rows, grid_keys)
    files["report"].write_text(report_markdown(result, grid_keys, spec_path))
    plot_ate(files["plot"], result.rows)
    files["json"].write_text(json.dumps({
        "spec": str(spec_path.resolve()), "executor": result.executor, "jobs": result.jobs,
        "wall_s": result.wall_s, "runs": len(result.rows), "ran": result.n_ran, "reused": result.n_reused,
        "failed": result.n_failed,
        "run_wall_s": {r.run_id: r.wall_s for r in result.rows if not r.reused},
    }, indent=2))
    return files


# ---------------------------------------------------------------------------- command line

EPILOG = """\
examples:
  python -m windowvo.batch eval.yaml                      # local, one process per CPU
  python -m windowvo.batch eval.yaml --jobs 4 --force     # rerun everything, 4 at a time
  python -m windowvo.batch eval.yaml --executor ray       # a local Ray instance
  python -m windowvo.batch eval.yaml --executor ray --address ray://head:10001   # a Ray cluster

The Ray executor needs `pip install "windowvo[cluster]"`; on a cluster, sequences and the output
root must be on storage every node mounts at the same path.
Exit codes: 0 every run ok, 1 some runs failed (see results.csv), 2 bad spec or executor.
"""
