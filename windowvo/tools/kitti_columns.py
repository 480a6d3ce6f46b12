"""The KITTI odometry metric as report columns (bench table, batch results.csv and report.md).

Two segment sets (:class:`~windowvo.eval.kitti_metric.SegmentSet`): the short one (10-80 m) for
recordings of tens of metres, and the devkit's 100-800 m, shown only when some run's ground-truth
path is long enough for one such segment (``n/a`` for the others). t_rel in %, r_rel in degrees per
100 m, mean over every segment (the devkit's definition). An estimate up to scale (monocular, not
metric) is scaled by its Sim(3) scale first, as ``windowvo.eval`` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..eval.kitti_metric import SegmentSet, kitti_odometry_error
from ..io.trajectory import Trajectory

NOT_AVAILABLE = "n/a"


@dataclass(frozen=True)
class KittiColumn:
    """One column: a segment set and a quantity (``t_rel_pct`` or ``r_rel_deg_per_100m``)."""

    segments: SegmentSet
    quantity: str
    header: str
    digits: int

    @property
    def key(self) -> str:
        """The flat key of a CSV column or a row dict, e.g. ``kitti_short_t_rel_pct``."""
        return f"kitti_{self.segments.value}_{self.quantity}"


KITTI_COLUMNS = (
    KittiColumn(SegmentSet.SHORT, "t_rel_pct", "t_rel % (10-80 m)", 2),
    KittiColumn(SegmentSet.SHORT, "r_rel_deg_per_100m", "r_rel deg/100 m (10-80 m)", 3),
    KittiColumn(SegmentSet.DEVKIT, "t_rel_pct", "t_rel % (100-800 m)", 2),
    KittiColumn(SegmentSet.DEVKIT, "r_rel_deg_per_100m", "r_rel deg/100 m (100-800 m)", 3),
)


def kitti_errors(groundtruth: Trajectory, estimate: Trajectory, sim3_scale: float | None = None) -> dict[str, dict]:
    """``{segment set: KittiOdometryError.as_dict()}`` for both segment sets; ``sim3_scale``: the scale of an
    estimate that is up to scale (None: metric). An unknown scale (not finite) or no matching poses: ``{}``."""
    from ..errors import WindowVOError

    scale = 1.0 if sim3_scale is None else float(sim3_scale)
    if not math.isfinite(scale) or scale <= 0:
        return {}
    try:
        return {s.value: kitti_odometry_error(groundtruth, estimate, s, estimate_scale=scale).as_dict()
                for s in SegmentSet}
    except WindowVOError:
        return {}


def flat_values(kitti: dict[str, dict] | None) -> dict[str, float | None]:
    """The column values (``KittiColumn.key`` -> number or None) of a :func:`kitti_errors` result."""
    out: dict[str, float | None] = {}
    for c in KITTI_COLUMNS:
        block = (kitti or {}).get(c.segments.value) or {}
        v = block.get(c.quantity)
        out[c.key] = float(v) if isinstance(v, (int, float)) and block.get("n_segments") else None
    return out


def has_devkit_segments(kittis: list[dict[str, dict] | None]) -> bool:
    """Some run's ground truth is long enough for a 100-800 m segment (else the devkit columns are left out)."""
    return any(((k or {}).get(SegmentSet.DEVKIT.value) or {}).get("n_segments") for k in kittis)


def shown_columns(kittis: list[dict[str, dict] | None]) -> tuple[KittiColumn, ...]:
    """The short-segment columns, and the devkit ones when any run has a devkit segment."""
    devkit = has_devkit_segments(kittis)
    return tuple(c for c in KITTI_COLUMNS if c.segments is SegmentSet.SHORT or devkit)


def cell(kitti: dict[str, dict] | None, column: KittiColumn) -> str:
    """A table cell: the number, ``n/a`` when the path is too short for that segment set, blank when unknown."""
    block = (kitti or {}).get(column.segments.value)
    if not block:
        return ""
    v = block.get(column.quantity)
    if not block.get("n_segments") or not isinstance(v, (int, float)):
        return NOT_AVAILABLE
    return f"{v:.{column.digits}f}"
