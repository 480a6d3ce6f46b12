"""The floor's depth states ``D(k)`` (``ground.height_sigma_fraction``): how far the true floor lies below the one
the configured camera height puts under the base, shared by the keyframes, with a prior and a slow random walk.

Why a state: a constant error of the camera height is a constant error of the floor's scale, and it is shared by
every floor point of the run. Tied each to the configured floor, 100 points would claim the scale to a few tenths
of a percent; through one depth whose prior says how well the height is known, the floor tells the scale no better
than that prior, and with wheels the fused scale weighs the floor against the wheel calibration's own prior.

Lifecycle (the window's rules, as for the wheel calibration ``C(k)``): the chain starts at the first keyframe that
ties floor points (a prior); from then on every keyframe refreshes the live state's stamp, a new state starts with
each block of keyframes that leave the window together, joined to the last by a random walk, so the chain never
breaks and no state is left without a factor; a window reset restarts it with its prior around the last estimate.
"""

from __future__ import annotations

import gtsam
import numpy as np

from ..config import BackendConfig
from . import factors as fac
from .factors import D


class FloorDepthStates:
    """The depth chain of one back end (live only with ``ground.height_sigma_fraction``)."""

    def __init__(self, cfg: BackendConfig, camera_height_m: float):
        g = cfg.ground
        self.cfg = cfg
        self.wanted = g.height_sigma_fraction is not None  # never with floor_state (the config refuses both)
        self.prior_sigma_m = (g.height_sigma_fraction or 0.0) * camera_height_m
        self.walk_m = g.height_walk_per_sqrt_m * camera_height_m
        self.key = -1  # keyframe index of the live state D(key); -1: the chain has not started (or was reset)
        self.depth_m = 0.0  # its last estimate
        self._at: np.ndarray | None = None  # where the base was when D(key) started (its random walk's distance)
        self.estimated = False  # the chain has started at least once (depth_m is an estimate)

    @property
    def live(self) -> bool:
        return self.key >= 0

    def start(self, graph, values, stamps: dict[int, float], k: int, T_guess: np.ndarray) -> int:
        """Keyframe k ties floor points: the live state's key, starting the chain (its prior) if it is not live."""
        if not self.live:
            values.insert(D(k), float(self.depth_m))
            stamps[D(k)] = float(k)
            graph.add(fac.floor_depth_prior(k, self.depth_m, self.prior_sigma_m))
            self.key, self._at = k, T_guess[:3, 3].copy()
            self.estimated = True
        return D(self.key)

    def step(self, graph, values, stamps: dict[int, float], k: int, T_guess: np.ndarray) -> None:
        """Every keyframe once the chain is live: refresh the live state's stamp, or start the block's new state."""
        if not self.live or k == self.key:
            return
        if not fac.block_starts(self.cfg, k):
            stamps[D(self.key)] = float(k)
            return
        assert self._at is not None
        dist = float(np.linalg.norm(T_guess[:3, 3] - self._at))
        values.insert(D(k), float(self.depth_m))
        stamps[D(k)] = float(k)
        graph.add(fac.floor_depth_walk(self.key, k, self.walk_m * np.sqrt(max(dist, 1e-3))))
        self.key, self._at = k, T_guess[:3, 3].copy()

    def read(self, est: gtsam.Values) -> None:
        if self.live and est.exists(D(self.key)):
            self.depth_m = float(est.atDouble(D(self.key)))

    def reset(self) -> None:
        """A fresh smoother holds no depth state: the chain restarts at the next floor tie, around ``depth_m``."""
        self.key, self._at = -1, None
