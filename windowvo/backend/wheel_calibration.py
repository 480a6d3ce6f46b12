"""The back end's wheel calibration states ``C(k)``: when they are live, which one a wheel step goes through,
their prior and random walk, their estimate and marginal sigmas, and what a window reset does to them.

``C(k)`` is the wheel calibration (distance scale, yaw bias per metre, yaw scale) from keyframe k on, one per block of
keyframes that leave the window together (``WheelCalibrationStates.state``). The states start with the first
floor landmarks (``start_with_floor``): before, nothing but the wheels could fix the scale, so a free wheel
scale would drift (measured on KITTI, where the road is seldom tracked). The window (``smoother.py``) owns the
keys' timestamps and the smoother; this module only adds the states' values, stamps and factors to an update.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from ..config import BackendConfig
from ..types import WheelCalibration
from . import factors as fac
from .factors import C

log = logging.getLogger(__name__)

# After a reset the calibration restarts from its last estimate with this share of the prior sigmas.
RESET_CALIBRATION_SIGMA_FACTOR = 0.2


class WheelCalibrationStates:
    """The calibration states C(k) of one back end (live only with wheels and ``wheel_calibration.enabled``)."""

    def __init__(self, cfg: BackendConfig, use_odometry: bool):
        self.cfg = cfg
        self.wanted = use_odometry and cfg.wheel_calibration.enabled
        self.calibrate = False  # the calibration states C(k) are live
        self.start = -1  # keyframe the calibration started (or restarted) at
        self.key = -1  # keyframe index of the live calibration state C(key)
        self.distance_m = 0.0  # driven since C(key) was created (its random walk)
        wc = cfg.wheel_calibration
        self.calib = WheelCalibration(wc.initial_scale, wc.initial_yaw_bias_per_m, yaw_scale=wc.initial_yaw_scale)

    def start_with_floor(self, k: int, n_ground_keyframes: int) -> None:
        """Start the online calibration at keyframe k once floor points have been tied at some keyframe."""
        if self.wanted and not self.calibrate and n_ground_keyframes > 0:
            self.calibrate, self.start = True, k
            log.info("keyframe %d: the floor is in view; wheel scale, yaw bias and yaw scale are now estimated online",
                     k)

    def block_starts(self, k: int) -> bool:
        """A new calibration state starts with each block of keyframes that leaves the window together."""
        return fac.block_starts(self.cfg, k)

    def state(self, graph, values, stamps: dict[int, float], k: int) -> int:
        """Key of the calibration state keyframe k's wheel step goes through.

        One state per block of ``marginalize_every`` keyframes (the blocks that leave the window
        together), not per keyframe: the calibration drifts over tens of metres, a block spans a
        metre or two, and every extra state joins the dense block of poses iSAM2 re-eliminates at
        each update (one per keyframe made the back end ~50% slower). A new state ``C(k)`` joins with
        a prior (the first one) or a random walk from the previous one, so the chain never breaks; a
        state in use has its timestamp refreshed, so it leaves with the last pose whose step it holds."""
        if k != self.start and self.key >= 0 and not self.block_starts(k):
            stamps[C(self.key)] = float(k)
            return C(self.key)
        values.insert(C(k), self._vector())
        stamps[C(k)] = float(k)
        if k == self.start or self.key < 0:
            graph.add(fac.calibration_prior(k, self._vector(), self._prior_sigmas()))
        else:
            graph.add(fac.calibration_random_walk(self.cfg, self.key, k, self.distance_m))
        self.key, self.distance_m = k, 0.0
        return C(k)

    def step_key(self, graph, values, stamps: dict[int, float], k: int, distance_m: float | None) -> int | None:
        """The calibration key keyframe k's wheel step goes through (None: not calibrating), and the distance
        of that step (None: no wheel reading) added to the live state's random walk."""
        calib_key = self.state(graph, values, stamps, k) if self.calibrate else None
        if calib_key is not None and distance_m is not None:
            self.distance_m += distance_m
        return calib_key

    def _vector(self) -> np.ndarray:
        """The calibration as the state's value: (scale, yaw bias per metre, yaw scale)."""
        return np.array([self.calib.scale, self.calib.yaw_bias_per_m, self.calib.yaw_scale])

    def _prior_sigmas(self, factor: float = 1.0) -> np.ndarray:
        wc = self.cfg.wheel_calibration
        return factor * np.array([wc.scale_prior_sigma, wc.yaw_bias_prior_sigma, wc.yaw_scale_prior_sigma])

    def read(self, est: gtsam.Values) -> None:
        """Take the live state's estimate."""
        if self.calibrate and est.exists(C(self.key)):
            c = est.atPoint3(C(self.key))
            self.calib.scale, self.calib.yaw_bias_per_m, self.calib.yaw_scale = float(c[0]), float(c[1]), float(c[2])

    def with_sigma(self, smoother, est: gtsam.Values | None) -> WheelCalibration:
        """The newest calibration estimate with its marginal sigmas (computed on request: costs a solve)."""
        cal = WheelCalibration(self.calib.scale, self.calib.yaw_bias_per_m, yaw_scale=self.calib.yaw_scale)
        if self.calibrate and est is not None and est.exists(C(self.key)):
            try:
                sig = np.sqrt(np.diag(smoother.marginalCovariance(C(self.key))))
                cal.scale_sigma, cal.yaw_bias_sigma, cal.yaw_scale_sigma = (float(v) for v in sig)
            except RuntimeError as err:  # pragma: no cover - diagnostics only
                log.debug("no marginal covariance of the calibration: %s", err)
        return cal

    # ------------------------------------------------------------------ window reset
    def forget_failed_start(self, k: int) -> None:
        """A window restart at keyframe k: a calibration that started in the failed update is undone."""
        if self.calibrate and self.start >= k:
            self.calibrate, self.start, self.key = False, -1, -1

    def restart_from_previous(self, graph, values, stamps: dict[int, float], k: int) -> None:
        """A window restarting from keyframe k - 1: the calibration restarts there from its last estimate with
        ``RESET_CALIBRATION_SIGMA_FACTOR`` of the prior sigmas."""
        if not self.calibrate:
            return
        values.insert(C(k - 1), self._vector())
        stamps[C(k - 1)] = float(k - 1)
        graph.add(fac.calibration_prior(k - 1, self._vector(), self._prior_sigmas(RESET_CALIBRATION_SIGMA_FACTOR)))
        self.key, self.distance_m = k - 1, 0.0

    def restart_here(self, graph, values, stamps: dict[int, float], k: int) -> None:
        """A window restarting from keyframe k alone: the chain restarts here from the last estimate with the
        full prior."""
        if self.calibrate:
            self.start = k
            self.state(graph, values, stamps, k)
