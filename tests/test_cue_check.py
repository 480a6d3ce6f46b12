"""Floor against wheels (backend/cue_check.py): the chi-square test of the scale each cue implies."""

from __future__ import annotations

import math

import pytest

from windowvo.backend.cue_check import CueCheck
from windowvo.config import CueCheckConfig

HEIGHT_M = 0.45


def _check(**cfg) -> CueCheck:
    return CueCheck(CueCheckConfig(**cfg), HEIGHT_M, wheel_scale_sigma=0.03, floor_sigma_fraction=0.015)


def _drive(check: CueCheck, n: int, wheel_scale: float, floor_scale: float, step_m: float = 0.2):
    """n keyframes: the estimate moves step_m, the wheels read wheel_scale x that, the floor plane lies at the
    height that makes floor_scale the scale the floor implies (h_known / h_estimate)."""
    out = []
    for k in range(1, n + 1):
        out.append(check.observe(k, wheel_scale * step_m, step_m, HEIGHT_M / floor_scale))
    return out


def test_agreeing_cues_pass_and_the_disagreement_is_their_ratio():
    check = _check()
    res = _drive(check, 12, wheel_scale=1.02, floor_scale=1.0)
    assert res[0] is None  # 0.2 m driven: below min_distance_m (0.3 m)
    last = res[-1]
    assert last is not None and last.agree
    # The floor's scale over the wheels': 1.0 / 1.02 - 1.
    assert last.disagreement == pytest.approx(1.0 / 1.02 - 1.0, abs=1e-9)
    assert check.share_agreeing() == 1.0
    assert not check.floor_gated()
    untested = _check()
    assert untested.floor_gated()  # the floor is tied only once a test passed


def test_a_camera_height_ten_percent_off_is_found_and_gates_the_floor():
    check = _check()
    res = _drive(check, 12, wheel_scale=1.0, floor_scale=1.10)
    tested = [r for r in res if r is not None]
    assert tested and not any(r.agree for r in tested)
    assert tested[-1].disagreement == pytest.approx(0.10, abs=1e-9)
    # chi-square: log(1.1)^2 / (0.03^2 + 0.015^2 / n) well past the 99% quantile (6.63).
    assert tested[-1].chi2 > 6.63
    assert check.disagree_since == tested[0].keyframe
    assert check.floor_gated()
    assert check.share_agreeing() == 0.0


def test_gate_off_only_reports():
    assert not _check(gate=False).floor_gated()
    check = _check(gate=False)
    _drive(check, 12, wheel_scale=1.0, floor_scale=1.10)
    assert check.disagree_since is not None and not check.floor_gated()


def test_agreement_again_ends_the_disagreement():
    check = _check(stretch_keyframes=3)
    _drive(check, 6, wheel_scale=1.0, floor_scale=1.12)
    assert check.floor_gated()
    for k in range(7, 12):
        check.observe(k, 0.2, 0.2, HEIGHT_M)
    assert not check.floor_gated() and check.disagree_since is None


def test_a_wheel_gap_restarts_the_stretch_and_no_plane_tests_nothing():
    check = _check()
    _drive(check, 5, wheel_scale=1.0, floor_scale=1.0)
    assert check.observe(6, None, 0.2, HEIGHT_M) is None
    assert check.observe(7, 0.2, 0.2, HEIGHT_M) is None  # 0.2 m since the gap
    fresh = _check()
    assert all(fresh.observe(k, 0.2, 0.2, None) is None for k in range(1, 10))
    assert math.isnan(fresh.share_agreeing())


def test_the_threshold_is_the_chi_square_quantile():
    assert _check(confidence=0.95).threshold == pytest.approx(3.841, abs=1e-3)
    assert _check(confidence=0.99).threshold == pytest.approx(6.635, abs=1e-3)


def test_lengths_measured_later_fill_the_stretchs_missing_heights():
    """``revise``: keyframes whose floor height was missing (the region's step held back until its pitch was tested)
    get the height their measured length implies against the estimate's step as stored; the next test counts them.
    A keyframe that had a height keeps it."""
    check = _check()
    assert [check.observe(k, 0.2, 0.2, None) for k in range(1, 5)] == [None] * 4  # no height: nothing tested
    check.revise({1: 0.21, 2: 0.21, 3: 0.21, 4: 0.21, 9: 0.5})  # the floor: each step 5% longer (9: not in it)
    res = check.observe(5, 0.2, 0.2, None)
    assert res is not None and res.disagreement == pytest.approx(0.05, abs=1e-9)  # the floor's 1.05 over the wheels'
    kept = _check()
    kept.observe(1, 0.2, 0.2, HEIGHT_M)
    kept.revise({1: 0.3})
    res = kept.observe(2, 0.2, 0.2, None)
    assert res is not None and res.disagreement == pytest.approx(0.0, abs=1e-9)
