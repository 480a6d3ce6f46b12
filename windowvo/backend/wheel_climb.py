"""The wheel steps' climb rate (``backend.odometry.climb_sigma_per_m``): which two consecutive wheel steps are tied
by their change of climb rate (``factors.climb_change_factor``). A ground robot moves along its floor: in the set-up's
base frame it climbs at a rate set by the mount's error (constant), the floor's slope and the suspension's load (slow),
so the rate's change between steps is the measurement, not the rate (docs/scale_suite.md, "The wheels' climb rate")."""

from __future__ import annotations

from ..config import BackendConfig
from . import factors as fac


class WheelClimb:
    """The last wheel step tied (its keyframe and distance); ``add`` ties the next one to it."""

    def __init__(self, cfg: BackendConfig):
        self.cfg = cfg
        self.last: tuple[int, float] | None = None
        self.slot: int | None = None  # this update's climb factor's place in its graph, if one was added

    def add(self, graph, k: int, distance_m: float, restart: bool, window_start: int) -> None:
        """Wheel step k-1 -> k (``distance_m``) was tied: tie it to step k-2 -> k-1 when that one was tied too, both
        were driven (``CLIMB_MIN_STEP_M`` each), keyframe k-2 is newer than the window's oldest after this update
        (``window_start``; as the region's range factors) and the window did not restart at k."""
        prev, self.last, self.slot = self.last, (k, distance_m), None
        if (self.cfg.odometry.climb_sigma_per_m <= 0 or restart or prev is None or prev[0] != k - 1
                or min(prev[1], distance_m) < fac.CLIMB_MIN_STEP_M or k - 2 <= window_start):
            return
        graph.add(fac.climb_change_factor(self.cfg, k, prev[1], distance_m))
        self.slot = graph.size() - 1

    def switched(self, new_indices: list[int]) -> list[int]:
        """This update's wheel step was taken for slip (``wheel_slip.py``): the smoother's index of its climb factor,
        to be removed with its planar one (a slipping step's climb rate is divided by the slipping distance), and
        the next step is not tied to it. ``new_indices``: the smoother's indices of this update's factors."""
        slot, self.slot, self.last = self.slot, None, None
        return [] if slot is None else [int(new_indices[slot])]
