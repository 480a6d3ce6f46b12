"""Two scale-suite results compared: does a setting change the fused and floor-only runs beyond chance? (issue #26)

``python -m windowvo.bench --suite scale --out DIR`` writes ``DIR/scale/scale_suite.json``: per sequence, each way's
ATE (the median over the floor's RANSAC seeds with ``--seeds N``, and each seed's run). A change is judged on the
whole suite, as a distribution: per way, the geometric mean and the worst of the ratios after / before (over all
sequences and per scene), and the suite's summary figures side by side. One run's ATE moves by chance (the floor's
RANSAC seed alone moves a floor-only run by more than 10% on half the sequences), so with seeded results each
sequence also says whether its new median lies outside the range of the old seeds' runs: ``beyond_seeds`` counts
those better and worse, the changes that chance alone did not make on the old runs.

Pure: reading the two files and the command line are in :mod:`windowvo.cli.scale_compare`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# The ways a setting of the floor or the fusion changes (the wheels-only way runs without the floor).
COMPARED_WAYS = ("fused", "floor")
# A sequence's change is marked in the table when its fused ratio lies beyond these.
MARK_WORSE = 1.25
MARK_BETTER = 0.8
# The suite's summary figures shown side by side (scale_suite.summary's keys).
SUMMARY_KEYS = ("fused_over_best_gmean", "fused_over_best_worst", "share_within_1.1x", "share_within_1.5x",
                "fused_worse_than_wheels_alone", "fused_se3_over_sim3_gmean", "kitti_fused_se3_over_sim3_worst")


@dataclass
class WayChange:
    """One way's ATE SE(3) ratios after / before over the common sequences."""

    way: str
    gmean: float
    worst: float
    worst_sequence: str
    best: float
    best_sequence: str
    by_scene: dict[str, float]  # scene -> geometric mean of its sequences' ratios
    beyond_seeds_better: int = 0  # new median below the old seeds' smallest run
    beyond_seeds_worse: int = 0  # ... above their largest


@dataclass
class SequenceChange:
    """One sequence before and after: ATE SE(3) (m) per compared way, and the suite's ratio fused / best single cue."""

    sequence: str
    scene: str
    before: dict[str, float]
    after: dict[str, float]
    fused_over_best: tuple[float, float]

    def ratio(self, way: str) -> float:
        return _ratio(self.after[way], self.before[way])


@dataclass
class ScaleComparison:
    """The result of ``compare``."""

    ways: list[WayChange]
    sequences: list[SequenceChange]
    summary: dict[str, tuple[float, float]]  # SUMMARY_KEYS present in both: (before, after)
    only_before: list[str] = field(default_factory=list)
    only_after: list[str] = field(default_factory=list)


def _ratio(after: float, before: float) -> float:
    return after / before if before > 0 and math.isfinite(before) and math.isfinite(after) else float("nan")


def _gmean(values: list[float]) -> float:
    v = [x for x in values if x > 0 and math.isfinite(x)]
    return float(np.exp(np.mean(np.log(v)))) if v else float("nan")


def _beyond_seeds(before: dict, after: dict) -> int:
    """-1 / +1 when the new median lies below / above every one of the old seeds' runs, else 0 (or without seeds)."""
    runs = [x for x in before.get("se3_runs", []) if math.isfinite(x)]
    new = after.get("se3", float("nan"))
    if len(runs) < 2 or not math.isfinite(new):
        return 0
    return -1 if new < min(runs) else (1 if new > max(runs) else 0)


def _way_change(way: str, rows_before: dict[str, dict], rows_after: dict[str, dict], names: list[str]) -> WayChange:
    ratios = {n: _ratio(rows_after[n][way]["se3"], rows_before[n][way]["se3"]) for n in names}
    finite = {n: r for n, r in ratios.items() if math.isfinite(r)}
    worst = max(finite, key=lambda n: finite[n]) if finite else ""
    best = min(finite, key=lambda n: finite[n]) if finite else ""
    scenes: dict[str, list[float]] = {}
    for n in names:
        scenes.setdefault(rows_before[n]["scene"], []).append(ratios[n])
    beyond = [_beyond_seeds(rows_before[n][way], rows_after[n][way]) for n in names]
    return WayChange(way, _gmean(list(ratios.values())), finite.get(worst, float("nan")), worst,
                     finite.get(best, float("nan")), best, {s: _gmean(v) for s, v in scenes.items()},
                     beyond.count(-1), beyond.count(1))


def compare(before: dict, after: dict) -> ScaleComparison:
    """Compare two ``scale_suite.json`` contents (``{"rows": [...], "summary": {...}}``) on their common sequences,
    in the order of ``before``."""
    rows_before = {r["sequence"]: r for r in before["rows"]}
    rows_after = {r["sequence"]: r for r in after["rows"]}
    names = [n for n in rows_before if n in rows_after]
    sequences = [SequenceChange(n, rows_before[n]["scene"],
                                {w: rows_before[n][w]["se3"] for w in COMPARED_WAYS},
                                {w: rows_after[n][w]["se3"] for w in COMPARED_WAYS},
                                (rows_before[n]["fused_over_best"], rows_after[n]["fused_over_best"]))
                 for n in names]
    sb, sa = before.get("summary", {}), after.get("summary", {})
    return ScaleComparison(
        ways=[_way_change(w, rows_before, rows_after, names) for w in COMPARED_WAYS],
        sequences=sequences,
        summary={k: (float(sb[k]), float(sa[k])) for k in SUMMARY_KEYS if k in sb and k in sa},
        only_before=[n for n in rows_before if n not in rows_after],
        only_after=[n for n in rows_after if n not in rows_before])


def _f(v: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.{digits}f}"


def comparison_text(c: ScaleComparison) -> str:
    """The comparison as a user reads it: per way the distribution, then a row per sequence, then the summary."""
    lines = [f"{len(c.sequences)} common sequences"
             + (f"; only before: {', '.join(c.only_before)}" if c.only_before else "")
             + (f"; only after: {', '.join(c.only_after)}" if c.only_after else "")]
    for w in c.ways:
        scenes = ", ".join(f"{s} {_f(g)}x" for s, g in w.by_scene.items())
        lines.append(f"{w.way}: after / before ATE SE(3) geometric mean {_f(w.gmean)}x, worst {_f(w.worst, 2)}x "
                     f"({w.worst_sequence}), best {_f(w.best, 2)}x ({w.best_sequence}); {scenes}; beyond the old "
                     f"seeds' runs: {w.beyond_seeds_better} better, {w.beyond_seeds_worse} worse")
    lines += ["", "| sequence | fused before | after | ratio | floor only before | after | ratio | "
                  "fused / best single cue before | after |", "|---|---|---|---|---|---|---|---|---|"]
    for s in c.sequences:
        r = s.ratio("fused")
        mark = " (worse)" if r > MARK_WORSE else (" (better)" if r < MARK_BETTER else "")
        lines.append(f"| {s.sequence} | {_f(s.before['fused'])} | {_f(s.after['fused'])} | {_f(r, 2)}x{mark} | "
                     f"{_f(s.before['floor'])} | {_f(s.after['floor'])} | {_f(s.ratio('floor'), 2)}x | "
                     f"{_f(s.fused_over_best[0], 2)}x | {_f(s.fused_over_best[1], 2)}x |")
    lines.append("")
    lines += [f"{k}: {_f(b)} -> {_f(a)}" for k, (b, a) in c.summary.items()]
    return "\n".join(lines)
