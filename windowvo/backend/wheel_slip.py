"""Slip and skids: a wheel step the window's own solution rejects is switched off (issue #26 item 3).

The wheel factor (``factors.odometry_factors``) assumes each step's error is small and independent, under a robust
loss so that vision can overrule a bad one. Slip is neither: a wheel spinning on a wet patch reports 30-50% too
much distance for a second or more, step after step, and the robust loss still gives each slipping step a small
weight (Cauchy: a few percent at 15 sigma) evaluated at the linearization point the wheels themselves set (the
initial guess follows the wheels). Over a slip window those weights add up: the estimate is pulled forward by
centimetres, the wheel calibration's scale moves by 1.5-3%, and the floor-against-wheels test sees a scale change
that is not there.

So after each keyframe's update the new wheel step is checked against the window's solution, which holds vision,
the floor and the earlier steps: the planar residual (yaw, x, y) of its factor at the solution, in the step's own
sigmas (``factors.wheel_step_sigmas``). Beyond the chi-square quantile at ``backend.odometry.slip_switch_confidence``
(0.9999: 4.6 sigma; a switch is a hard decision, for gross errors only, the robust loss weighs the rest) the step
is taken for slip or a skid: its planar factor is removed and the window solved again without
it (a switchable constraint whose switch is decided once, on the solution, instead of a weight re-decided at each
linearization). A slip is a distance error: when the step's heading alone agrees with the solution (its own 1-D
residual within the chi-square threshold) the heading is kept and only the distance left free; otherwise (a
skid) nothing of the step's plane is kept. The step's vertical part stays ("the robot drives on its wheels": loose, it keeps the window
linked), and so does the calibration state's random walk, so no key loses its factors; its climb tie
(``backend.odometry.climb_sigma_per_m``, ``wheel_climb.py``) goes with the planar factor. A switched step is left
out of the floor-against-wheels test (``cue_check.py``): a slipping wheel says nothing about the tyre's scale.

Only a step that goes through the wheel calibration is judged, i.e. once the floor is in view and holds the
window's scale: where the wheels alone set the scale, the solution's scale is the wheels' own history, a slip
pulls the solution with it, and the correct steps after it would be judged against the slipped scale (on
held-out streets, where the floor is never tied, judging them made runs 2-15x worse). And only at a keyframe with
at least ``slip_switch_min_observations`` projection factors: where vision hardly sees the step, the solution may
be the wrong one (a rocking base's feature simulation: steps 7-12 sigma off at keyframes with 2-7 observations,
switched off, took a run from 0.011 to 3.4 m). Elsewhere, where vision is weak, the solution follows the wheels,
their residuals stay small and nothing is switched: the wheels carry the run, as before.

While the last judged step is switched off (``in_slip``), the next keyframe's initial guess is PnP's pose where
PnP and the wheels disagree (``SlidingWindowBackend._initial_guess``; elsewhere a PnP pose the wheel factor would
reject is not followed): a slip lasts longer than one keyframe, and a solve started from the slipping wheels' pose
ended a few millimetres long.

Reported per keyframe in ``stats.csv`` (``wheel_step_sigmas``, ``wheel_slip``) and over the run in the summary
(``wheel_slip``: the steps switched off and the frames they span).
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from ..config import BackendConfig
from ..types import OdometryStep
from . import factors as fac

log = logging.getLogger(__name__)


class SlipAction(str, enum.Enum):
    """What a judged wheel step keeps."""

    KEPT = "kept"  # within the threshold: the step's factor stays
    HEADING = "heading"  # its distance slipped, its heading agrees: only the heading is kept
    NONE = "none"  # its heading is off too (a skid): its planar factor is removed


@dataclass(frozen=True)
class SlipJudgement:
    """One keyframe's wheel step against the window's solution."""

    keyframe: int
    sigmas: float  # the planar residual's norm in the step's sigmas
    action: SlipAction

    @property
    def switched(self) -> bool:
        """Taken for slip: its planar factor was replaced (heading only) or removed."""
        return self.action is not SlipAction.KEPT


@dataclass(frozen=True)
class _Pending:
    slot: int  # the planar factor's position in this update's new factors
    k: int
    odom: OdometryStep
    calib_key: int | None  # the calibration state it goes through (None: a plain between-factor)


class WheelSlipSwitch:
    """Judges each keyframe's new wheel step on the window's solution (see the module's docstring)."""

    def __init__(self, cfg: BackendConfig):
        self.cfg = cfg
        o = cfg.odometry
        self.enabled = o.slip_switch
        self.threshold = (float(o.slip_switch_k) if o.slip_switch_k is not None
                          else fac.robust_threshold(3, o.slip_switch_confidence))
        self.heading_threshold = fac.robust_threshold(1, o.slip_switch_confidence)  # the heading's own residual
        self.min_observations = o.slip_switch_min_observations
        self._pending: _Pending | None = None
        self.last: SlipJudgement | None = None  # this keyframe's judgement (None: no wheel step judged)
        self._in_slip = False

    def begin_update(self) -> None:
        """A new keyframe: nothing judged yet."""
        self._pending, self.last = None, None

    def expect(self, slot: int, k: int, odom: OdometryStep, calib_key: int | None) -> None:
        """This update's graph holds keyframe k's wheel step's planar factor at position ``slot`` of its new
        factors."""
        if self.enabled:
            self._pending = _Pending(slot, k, odom, calib_key)

    def forget(self) -> None:
        """The window was reset: the pending step's factor is gone with the old smoother."""
        self._pending, self._in_slip = None, False

    def judge(self, frame_index: int, smoother, estimate: gtsam.Values | None, new_indices: list[int],
              n_observations: int) -> tuple[int, gtsam.NonlinearFactorGraph] | None:
        """When the solution ``estimate`` rejects the new wheel step: the smoother's index of its planar factor
        (to be removed) and what replaces it (its heading alone, or nothing); else None. Records the judgement
        in ``last``. A step whose keyframe holds fewer than ``slip_switch_min_observations`` projection factors
        (``n_observations``) is not judged: vision does not constrain it, and a wrong solution would switch good
        wheels off."""
        p, self._pending = self._pending, None
        if p is None or estimate is None or p.slot >= len(new_indices) or n_observations < self.min_observations:
            return None
        index = int(new_indices[p.slot])
        r = fac.wheel_step_sigmas(self.cfg, smoother.getFactors().at(index), estimate, p.odom.T_prev_cur,
                                  p.odom.distance_m, p.calib_key is not None)
        z = float(np.linalg.norm(r))
        replace = gtsam.NonlinearFactorGraph()
        if not np.isfinite(z) or z <= self.threshold:
            action = SlipAction.KEPT
        elif abs(float(r[0])) <= self.heading_threshold:
            action = SlipAction.HEADING
            replace.add(fac.odometry_factors(self.cfg, p.k, p.odom.T_prev_cur, p.odom.distance_m, p.calib_key,
                                             heading_only=True)[-1])
        else:
            action = SlipAction.NONE
        self.last = SlipJudgement(p.k, z, action)
        if self.last.switched and not self._in_slip:
            log.warning("keyframe %d (frame %d): the wheel step lies %.1f sigma off the window's solution (> %.1f): "
                        "taken for slip, its %s while the wheels disagree", p.k, frame_index, z, self.threshold,
                        "distance left out" if action is SlipAction.HEADING else "planar factor switched off")
        elif not self.last.switched and self._in_slip:
            log.info("keyframe %d (frame %d): the wheels agree with the window's solution again (%.1f sigma)",
                     p.k, frame_index, z)
        self._in_slip = self.last.switched
        return (index, replace) if self.last.switched else None

    @property
    def in_slip(self) -> bool:
        """The last judged wheel step was switched off (the wheels are slipping, as far as the window knows)."""
        return self._in_slip

    @property
    def switched_now(self) -> bool:
        """This keyframe's wheel step was switched off."""
        return self.last is not None and self.last.switched
