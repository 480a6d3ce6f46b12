"""Floor and wheels checked against each other: does the scale the floor implies agree with the wheels'?

Both cues tell the metric scale, each through a different systematic error: the wheels through their distance
scale (a tyre's radius, known a priori to a few percent, ``wheel_calibration.scale_prior_sigma``), the floor through
the camera's height above it (the configured height, the suspension, a raised surface taken for the floor).
Against the window's estimate, at each keyframe where both are measured over the last ``stretch_keyframes``:

* the wheels say the estimate's scale is off by ``D_wheels / D_estimate`` (their raw, uncalibrated distance over
  the stretch against the estimate's);
* the floor says it is off by ``h_known / h_estimate`` (the known camera height against the height of the floor
  planes fitted in the estimate over the stretch, each keyframe's fit: ``FloorModel.floor_of``; where no plane is
  fitted, the height the floor's region implies, ``RoadRegion.after_update``, once the floor's pitch it is measured
  on has been tested: a step measured before is measured again then, and the height its length implies is given to
  its keyframe's entry of the stretch, ``CueCheck.revise``).

Their ratio ``(D_estimate h_known) / (D_wheels h_estimate)`` does not depend on the estimate's scale, so it is a
test of the cues, not of the fusion. Its log has the variance of the wheel scale's prior plus the floor height's
(a keyframe's floor height, ``ground.sigma_common_fraction`` or else ``sigma_height_fraction``, over the stretch's
keyframes): the
chi-square of one degree of freedom at ``confidence`` decides. Vision cannot tell which scale is the right one
(it is up to scale); what does: the wheels' error is bounded by the tyre (a few percent), the floor's is not (a
mis-measured height, a kerb, a table top taken for the floor). So until a first test passes, and while they
disagree, the floor's new points are not tied to it (``gate``: a switch on the floor's factors, set by the test),
and the wheels carry the scale.

Pure numpy: tested on its own (``tests/test_cue_check.py``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

from ..config import CueCheckConfig
from .chi2 import chi2_quantile


@dataclass(frozen=True)
class CueAgreement:
    """One keyframe's test: the floor's scale against the wheels' (``disagreement``: their ratio less 1)."""

    keyframe: int
    disagreement: float  # (floor scale) / (wheel scale) - 1 over the stretch, e.g. 0.07: the floor says 7% larger
    chi2: float  # its square over its variance
    agree: bool  # chi2 within the test's threshold


@dataclass(frozen=True)
class _Step:
    keyframe: int
    wheel_m: float
    estimate_m: float
    floor_height_m: float | None  # the keyframe's floor plane fitted in the estimate (None: no plane)


class CueCheck:
    """The chi-square test of floor against wheels at each keyframe, over a stretch of the latest keyframes."""

    def __init__(self, cfg: CueCheckConfig, camera_height_m: float, wheel_scale_sigma: float,
                 floor_sigma_fraction: float):
        self.cfg = cfg
        self.camera_height_m = camera_height_m
        self.wheel_scale_sigma = wheel_scale_sigma
        self.floor_sigma_fraction = floor_sigma_fraction  # one keyframe's floor height, as a share of itself
        self.threshold = chi2_quantile(1, cfg.confidence)  # chi-square quantile, 1 degree of freedom
        self._steps: deque[_Step] = deque(maxlen=cfg.stretch_keyframes)
        self.tests: list[CueAgreement] = []
        self.disagree_since: int | None = None  # first keyframe of the current disagreement

    def observe(self, k: int, wheel_m: float | None, estimate_m: float, floor_height_m: float | None
                ) -> CueAgreement | None:
        """Keyframe k's wheel distance (raw), estimated distance and floor plane height (in the estimate) since
        keyframe k-1; returns the test over the stretch, or None when the stretch does not test anything yet."""
        if wheel_m is None or not math.isfinite(estimate_m):
            self._steps.clear()  # a wheel gap breaks the stretch
            return None
        self._steps.append(_Step(k, float(wheel_m), float(estimate_m), floor_height_m))
        result = agreement(k, list(self._steps), self.camera_height_m, self.wheel_scale_sigma,
                           self.floor_sigma_fraction, self.threshold, self.cfg.min_distance_m)
        if result is None:
            return None
        self.tests.append(result)
        if result.agree:
            self.disagree_since = None
        elif self.disagree_since is None:
            self.disagree_since = k
        return result

    def revise(self, lengths_m: dict[int, float]) -> None:
        """Steps of the stretch (by keyframe) whose metric length the floor measured later (the region's step held
        back until its floor pitch was tested): a keyframe without a floor height gets the one the length implies
        against the estimate's step as it was stored, ``h_known * estimate_m / length``; the next test counts it."""
        for i, s in enumerate(self._steps):
            length = lengths_m.get(s.keyframe)
            if s.floor_height_m is None and length is not None and length > 0:
                self._steps[i] = replace(s, floor_height_m=self.camera_height_m * s.estimate_m / length)

    def floor_gated(self) -> bool:
        """Whether the floor's new points stay untied (``gate`` on): the cues disagree now, or they were never
        tested yet (the floor is tied only once it has been checked: a wrong floor tied at the first keyframes
        would set the wheel calibration before any test could stop it)."""
        return self.cfg.gate and (self.disagree_since is not None or not self.tests)

    def share_agreeing(self) -> float:
        """Share of the tested keyframes whose cues agreed (nan: none tested)."""
        if not self.tests:
            return float("nan")
        return sum(t.agree for t in self.tests) / len(self.tests)


def agreement(k: int, steps: list[_Step], camera_height_m: float, wheel_scale_sigma: float,
              floor_sigma_fraction: float, threshold: float, min_distance_m: float) -> CueAgreement | None:
    """The test over ``steps`` (see the module's docstring); None without a floor plane or distance to test on."""
    heights = [s.floor_height_m for s in steps if s.floor_height_m is not None and s.floor_height_m > 0]
    d_wheel = sum(s.wheel_m for s in steps)
    d_est = sum(s.estimate_m for s in steps)
    if not heights or d_wheel < min_distance_m or d_est <= 0:
        return None
    h_est = math.exp(sum(math.log(h) for h in heights) / len(heights))
    log_ratio = math.log(d_est * camera_height_m / (d_wheel * h_est))  # log(floor scale / wheel scale)
    variance = wheel_scale_sigma**2 + floor_sigma_fraction**2 / len(heights)
    chi2 = log_ratio**2 / variance
    return CueAgreement(k, math.exp(log_ratio) - 1.0, chi2, chi2 <= threshold)
