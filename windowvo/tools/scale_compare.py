"""Two scale-suite results compared: does a setting change the fused and floor-only runs, and by more than chance?

``python -m windowvo.bench --suite scale --out DIR`` writes ``DIR/scale/scale_suite.json``: per sequence, each way's
ATE (the median over the floor's RANSAC seeds with ``--seeds N``, and each seed's run). A change is judged on the
whole suite, as a distribution (issue #26): per way, the geometric mean and the worst of the ratios after / before
(over all sequences and per scene; ratios that are not positive and finite are left out of the means), and the
suite's summary figures side by side.

One run's ATE moves by chance (the floor's RANSAC seed alone moves a floor-only run by more than 10% on half the
sequences). With seeded results on both sides each sequence also says whether its new median lies outside the range
of the old seeds' runs, below or above (``WayChange.beyond_seeds``). That alone is no test: with three seeds a change
that only draws the chance again puts the new median of three outside the old three's range 40% of the time, 20% on
each side (``chance_beyond_each_side``). A change shows in the two counts' difference, well past that share each.

Pure: reading the two files and the command line are in :mod:`windowvo.cli.scale_compare`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .scale_suite import SEEDED_WAYS, gmean

# A sequence's change is marked in the table when its fused ratio lies beyond these.
MARK_WORSE = 1.25
MARK_BETTER = 0.8


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
    # (better, worse): sequences whose new median lies below / above every one of the old seeds' runs; None when
    # either side has no seeded runs (``--seeds 1``), so nothing can be said
    beyond_seeds: tuple[int, int] | None = None
    chance_each_side: float = float("nan")  # the share of sequences either count reaches by chance alone


def chance_beyond_each_side(n_new: int, n_old: int) -> float:
    """The probability that the median of ``n_new`` runs lies below every one of ``n_old`` other runs when all are
    draws of one distribution (and as much above): the r = n_new // 2 + 1 smallest of the n_new + n_old exchangeable
    runs are all new ones, C(n_new, r) / C(n_new + n_old, r). Three and three: 0.2."""
    r = n_new // 2 + 1
    return math.comb(n_new, r) / math.comb(n_new + n_old, r)


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
    summary: dict[str, tuple[float, float]]  # the numeric summary figures in both results: (before, after)
    only_before: list[str] = field(default_factory=list)
    only_after: list[str] = field(default_factory=list)


def _ratio(after: float, before: float) -> float:
    return after / before if before > 0 and math.isfinite(before) and math.isfinite(after) else float("nan")


def _seeded(way: dict) -> bool:
    return len(way.get("se3_runs", [])) >= 2


def _beyond_seeds(before: dict, after: dict) -> int:
    """-1 / +1 when the new median lies below / above every one of the old seeds' finite runs, else 0."""
    runs = [float(x) for x in before.get("se3_runs", []) if math.isfinite(float(x))]
    new = float(after.get("se3", float("nan")))
    if not runs or not math.isfinite(new):
        return 0
    return -1 if new < min(runs) else (1 if new > max(runs) else 0)


def _way_change(way: str, sequences: list[SequenceChange], rows_before: dict[str, dict],
                rows_after: dict[str, dict]) -> WayChange:
    ratios = {s.sequence: s.ratio(way) for s in sequences}
    usable = {n: r for n, r in ratios.items() if r > 0 and math.isfinite(r)}
    worst = max(usable, key=lambda n: usable[n]) if usable else ""
    best = min(usable, key=lambda n: usable[n]) if usable else ""
    scenes: dict[str, list[float]] = {}
    for s in sequences:
        scenes.setdefault(s.scene, []).append(ratios[s.sequence])
    beyond, chance = None, float("nan")
    olds, news = [rows_before[n][way] for n in ratios], [rows_after[n][way] for n in ratios]
    if ratios and all(_seeded(o) and _seeded(w) for o, w in zip(olds, news)):
        signs = [_beyond_seeds(o, w) for o, w in zip(olds, news)]
        beyond = (signs.count(-1), signs.count(1))
        chance = chance_beyond_each_side(min(len(w["se3_runs"]) for w in news), min(len(o["se3_runs"]) for o in olds))
    return WayChange(way, gmean(list(ratios.values())), usable.get(worst, float("nan")), worst,
                     usable.get(best, float("nan")), best, {sc: gmean(v) for sc, v in scenes.items()}, beyond, chance)


def compare(before: dict, after: dict) -> ScaleComparison:
    """Compare two ``scale_suite.json`` contents (``{"rows": [...], "summary": {...}}``) on their common sequences,
    in the order of ``before``."""
    rows_before = {str(r["sequence"]): r for r in before["rows"]}
    rows_after = {str(r["sequence"]): r for r in after["rows"]}
    names = [n for n in rows_before if n in rows_after]
    sequences = [SequenceChange(n, str(rows_before[n]["scene"]),
                                {w: float(rows_before[n][w]["se3"]) for w in SEEDED_WAYS},
                                {w: float(rows_after[n][w]["se3"]) for w in SEEDED_WAYS},
                                (float(rows_before[n]["fused_over_best"]), float(rows_after[n]["fused_over_best"])))
                 for n in names]
    sb, sa = before.get("summary", {}), after.get("summary", {})
    numeric = (int, float)
    return ScaleComparison(
        ways=[_way_change(w, sequences, rows_before, rows_after) for w in SEEDED_WAYS],
        sequences=sequences,
        summary={k: (sb[k], sa[k]) for k in sb
                 if k in sa and isinstance(sb[k], numeric) and isinstance(sa[k], numeric)},
        only_before=[n for n in rows_before if n not in rows_after],
        only_after=[n for n in rows_after if n not in rows_before])


def _f(v: float, digits: int = 3, unit: str = "") -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.{digits}f}{unit}"


def _figure(v: float) -> str:
    return str(v) if isinstance(v, int) and not isinstance(v, bool) else _f(float(v))


def _beyond_text(w: WayChange, n: int) -> str:
    if w.beyond_seeds is None:
        return "beyond the old seeds' runs: n/a (a side without seeded runs)"
    better, worse = w.beyond_seeds
    return (f"beyond the old seeds' runs: {better} better, {worse} worse (chance alone: about "
            f"{w.chance_each_side * n:.0f} each, {100 * w.chance_each_side:.0f}% of {n})")


def comparison_text(c: ScaleComparison) -> str:
    """The comparison as a user reads it: per way the distribution, then a row per sequence, then the summary."""
    lines = [f"{len(c.sequences)} common sequences"
             + (f"; only before: {', '.join(c.only_before)}" if c.only_before else "")
             + (f"; only after: {', '.join(c.only_after)}" if c.only_after else "")]
    for w in c.ways:
        scenes = ", ".join(f"{s} {_f(g, unit='x')}" for s, g in w.by_scene.items())
        lines.append(f"{w.way}: after / before ATE SE(3) geometric mean {_f(w.gmean, unit='x')}, worst "
                     f"{_f(w.worst, 2, 'x')} ({w.worst_sequence or '-'}), best {_f(w.best, 2, 'x')} "
                     f"({w.best_sequence or '-'}); {scenes}; {_beyond_text(w, len(c.sequences))}")
    lines += ["", "| sequence | fused before | after | ratio | floor only before | after | ratio | "
                  "fused / best single cue before | after |", "|---|---|---|---|---|---|---|---|---|"]
    for s in c.sequences:
        r = s.ratio("fused")
        mark = " (worse)" if r > MARK_WORSE else (" (better)" if r < MARK_BETTER else "")
        lines.append(f"| {s.sequence} | {_f(s.before['fused'])} | {_f(s.after['fused'])} | {_f(r, 2, 'x')}{mark} | "
                     f"{_f(s.before['floor'])} | {_f(s.after['floor'])} | {_f(s.ratio('floor'), 2, 'x')} | "
                     f"{_f(s.fused_over_best[0], 2, 'x')} | {_f(s.fused_over_best[1], 2, 'x')} |")
    lines.append("")
    lines += [f"{k}: {_figure(b)} -> {_figure(a)}" for k, (b, a) in c.summary.items()]
    return "\n".join(lines)
