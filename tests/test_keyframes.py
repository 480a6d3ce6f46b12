"""Keyframe selection by information: parallax as an angle, and track loss over established tracks only.

Unit tests of ``keyframe_reason`` and its inputs, then end-to-end runs on fast forward motion (a rendered
street at 10 m/s and 10 Hz, the KITTI excerpt when ../shared/data has it), where a fresh corner is often lost
in the next frame and the old rule made a keyframe of nearly every frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from windowvo.config import KeyframeConfig
from windowvo.frontend.gates import MIN_COMMON_TRACKS, TrackShare, keyframe_reason, parallax_threshold_px
from windowvo.types import FrontendOutput, KeyframeReason


def frame_output(parallax_px: float, timestamp: float = 0.1) -> FrontendOutput:
    return FrontendOutput(frame_index=1, timestamp=timestamp, track_ids=np.arange(200),
                          pixels=np.zeros((200, 2)), pixels_undistorted=np.zeros((200, 2)),
                          track_ages=np.ones(200, np.int32), outlier_pixels=np.zeros((0, 2)), parallax_px=parallax_px)


def reason(parallax_px: float, share: TrackShare, focal_px: float, kc: KeyframeConfig,
           odom: tuple[float, float] | None = (1.0, 0.0)) -> KeyframeReason:
    return keyframe_reason(frame_output(parallax_px), share, 0.0, odom, False, focal_px, kc)


KEPT_ALL = TrackShare(n_common=200, n_keyframe=200, n_common_established=200, n_keyframe_established=200)


@pytest.mark.parametrize("focal_px, parallax_px, expected", [
    (340.0, 19.0, KeyframeReason.NONE),
    (340.0, 21.0, KeyframeReason.PARALLAX),
    (707.0, 30.0, KeyframeReason.NONE),       # 30 px at 707 px is 2.4 deg: less than 20 px at 340 px (3.4 deg)
    (707.0, 40.0, KeyframeReason.NONE),
    (707.0, 42.0, KeyframeReason.PARALLAX),   # the threshold there is 20 * 707 / 340 = 41.6 px
])
def test_parallax_threshold_is_an_angle(focal_px, parallax_px, expected):
    kc = KeyframeConfig(parallax_focal_px=340.0)
    assert reason(parallax_px, KEPT_ALL, focal_px, kc) is expected


def test_parallax_in_the_cameras_own_pixels_without_a_reference_focal():
    kc = KeyframeConfig()  # the default: pixels of the camera, whatever its focal length
    assert kc.parallax_focal_px is None and parallax_threshold_px(kc, 707.0) == kc.min_parallax_px
    assert reason(21.0, KEPT_ALL, 707.0, kc) is KeyframeReason.PARALLAX
    at_340 = KeyframeConfig(parallax_focal_px=340.0)
    assert parallax_threshold_px(at_340, 707.0) == pytest.approx(20.0 * 707.0 / 340.0)
    assert parallax_threshold_px(at_340, 340.0) == kc.min_parallax_px  # exactly: the rendered cameras keep theirs


def test_fresh_corners_lost_at_once_make_no_keyframe():
    """Fast forward motion: half the keyframe's tracks were corners detected in that very frame, and most of
    those are lost in the next one; its established tracks nearly all survive. That is no loss of what the
    keyframe knew, so no keyframe; over all tracks (the old rule) it was a track-loss keyframe."""
    share = TrackShare(n_common=110, n_keyframe=200, n_common_established=90, n_keyframe_established=100)
    assert share.tracked_ratio() == pytest.approx(0.9)
    assert reason(5.0, share, 707.0, KeyframeConfig()) is KeyframeReason.NONE
    old_rule = TrackShare(n_common=110, n_keyframe=200, n_common_established=110, n_keyframe_established=200)
    assert reason(5.0, old_rule, 707.0, KeyframeConfig()) is KeyframeReason.TRACK_LOSS


def test_losing_established_tracks_still_makes_a_keyframe():
    share = TrackShare(n_common=150, n_keyframe=200, n_common_established=50, n_keyframe_established=100)
    assert reason(5.0, share, 707.0, KeyframeConfig()) is KeyframeReason.TRACK_LOSS


def test_a_keyframe_of_fresh_tracks_only_counts_them_all():
    """The first keyframe (or one after every track was lost) has no established tracks: its loss is judged
    over all of them, or a view that lost everything would never be renewed."""
    few = MIN_COMMON_TRACKS - 1
    share = TrackShare(n_common=60, n_keyframe=200, n_common_established=few, n_keyframe_established=few)
    assert share.tracked_ratio() == pytest.approx(0.3)
    assert reason(5.0, share, 707.0, KeyframeConfig()) is KeyframeReason.TRACK_LOSS
    nothing_shared = TrackShare(n_common=0, n_keyframe=200, n_common_established=0, n_keyframe_established=0)
    assert reason(0.0, nothing_shared, 340.0, KeyframeConfig(), odom=None) is KeyframeReason.TRACK_LOSS


def test_standstill_and_interval_unchanged():
    kc = KeyframeConfig()
    still = frame_output(0.2, timestamp=5.0)
    assert keyframe_reason(still, KEPT_ALL, 0.0, (0.0, 0.0), False, 707.0, kc) is KeyframeReason.NONE
    assert still.standstill
    slow = frame_output(3.0, timestamp=1.5)
    assert keyframe_reason(slow, KEPT_ALL, 0.0, (0.5, 0.0), False, 707.0, kc) is KeyframeReason.INTERVAL
    assert keyframe_reason(slow, KEPT_ALL, 0.0, (0.5, 0.0), True, 707.0, kc) is KeyframeReason.LAST


# ------------------------------------------------------------------------------ end to end

KITTI06 = Path("/work/shared/data/kitti06_000-050")
OLD_RULE = {"min_track_age": 0, "parallax_focal_px": None}  # every track counts; parallax in the camera's pixels
ESTABLISHED = {"min_track_age": 1}  # track loss over the tracks that survived a frame
BY_INFORMATION = {"min_track_age": 1, "parallax_focal_px": 340.0}  # ... and parallax as an angle


def run(tmp_path: Path, name: str, data: dict, keyframes: dict):
    from windowvo.config import config_from_dict
    from windowvo.runtime.job import run_job

    cfg = config_from_dict({"progress": False, "run_mode": "sequential", "viz": {"rerun": "off"}, **data,
                            "output": str(tmp_path / name), "keyframes": keyframes})
    rep = run_job(cfg)
    return rep.result.n_keyframes / rep.result.n_frames, rep.accuracy


@pytest.fixture(scope="module")
def street(tmp_path_factory) -> Path:
    """A rendered street, 10 m/s at 10 Hz (the scene's defaults), at the scale suite's half-KITTI image."""
    from windowvo.synth.generate import SynthSpec, generate_sequence
    from windowvo.synth.scenes import SceneKind

    d = tmp_path_factory.mktemp("street") / "seq"
    generate_sequence(d, SynthSpec.for_scene(SceneKind.STREET, duration_s=6.0, width=613, height=185, fx=353.5,
                                             seed=311))
    return d


@pytest.mark.slow
def test_street_keyframes_by_information(street, tmp_path):
    """10 m/s at 10 Hz: over all tracks the keyframe's fresh corners, most lost in the next frame, made a
    keyframe of nearly two frames in three; counting established tracks only (and parallax as an angle),
    fewer than two in five, with the trajectory still within 0.5% of the 60 m driven (SE(3) ATE against the
    renderer's ground truth). Not the default: it costs accuracy across the scale suite (docs/performance.md)."""
    old_rate, _ = run(tmp_path, "old", {"sequence": str(street)}, OLD_RULE)
    rate, acc = run(tmp_path, "new", {"sequence": str(street)}, BY_INFORMATION)
    assert old_rate > 0.55
    assert rate < 0.40
    assert acc is not None and acc.ate_se3_rmse_m < 0.005 * acc.path_length_m


@pytest.mark.slow
@pytest.mark.skipif(not (KITTI06 / "poses.txt").is_file(), reason=f"KITTI excerpt not found: {KITTI06}")
def test_kitti06_keyframes_by_established_tracks(tmp_path):
    """The KITTI 06 excerpt (12 m/s, synthetic wheels +1%): every frame was a track-loss keyframe; over
    established tracks about every other one is, and the trajectory stays within 0.3% of the 60 m driven
    (it was 0.138 m with every frame a keyframe, 0.098 m here). The floor's region is off here: with it (the
    default) the defaults' keyframes give 0.072 m, but a keyframe every other frame 0.491 m: the region's first pitch
    searches on two-frame steps come out 0.5-0.6 deg above those on one-frame steps, the steps measured on that pitch
    3-5% short, and the wheel calibration follows (1.04 for 1.01); the region's pitch with long steps is left open
    (README, keyframes.min_track_age)."""
    data = {"sequence": str(KITTI06), "dataset": "kitti", "backend": {"ground": {"road_region": {"enabled": False}}},
            "odometry_synthesis": {"enabled": True, "scale_error": 0.01, "yaw_bias_per_m": 0.005}}
    old_rate, _ = run(tmp_path, "old", data, OLD_RULE)
    rate, acc = run(tmp_path, "new", data, ESTABLISHED)
    assert old_rate > 0.95
    assert rate < 0.55
    assert acc is not None and acc.ate_se3_rmse_m < 0.003 * acc.path_length_m
