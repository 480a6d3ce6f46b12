"""Keyframe selection and the quality gates a keyframe candidate must pass before vision is used.

``keyframe_reason`` says why a frame should become a keyframe (parallax, track loss, interval, the last
frame) or that it should not (a standstill: little parallax and still wheels); ``apply_gates`` checks the
candidate (features, spread, inlier ratio, rotation-compensated parallax, cheirality). Thresholds:
``keyframes.*`` and ``gates.*`` in the config.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..config import GateConfig, KeyframeConfig
from ..types import FrontendOutput, GateOutcome, KeyframeReason

# Fewest tracks shared with the last keyframe for a two-view geometry, or for judging a standstill.
MIN_COMMON_TRACKS = 8


@dataclass(frozen=True)
class TrackShare:
    """How many of the last keyframe's tracks this frame still shares, over all of them and over the ones
    established at the keyframe (``keyframes.min_track_age``)."""

    n_common: int
    n_keyframe: int
    n_common_established: int
    n_keyframe_established: int

    def tracked_ratio(self) -> float:
        """Share of the keyframe's established tracks still tracked (of all its tracks if it had too few)."""
        if self.n_keyframe_established >= MIN_COMMON_TRACKS:
            return self.n_common_established / self.n_keyframe_established
        return self.n_common / max(self.n_keyframe, 1)


def parallax_threshold_px(kc: KeyframeConfig, focal_px: float) -> float:
    """The median parallax (pixels of a camera of focal length ``focal_px``) that makes a keyframe: the angle
    ``min_parallax_px / parallax_focal_px``, so a longer lens needs proportionally more pixels; without
    ``parallax_focal_px``, ``min_parallax_px`` of the camera's own pixels."""
    if kc.parallax_focal_px is None:
        return kc.min_parallax_px
    return kc.min_parallax_px * focal_px / kc.parallax_focal_px


def keyframe_reason(out: FrontendOutput, share: TrackShare, keyframe_time: float,
                    odom_motion: tuple[float, float] | None, force: bool, focal_px: float,
                    kc: KeyframeConfig) -> KeyframeReason:
    """Why this frame should be a keyframe (``KeyframeReason.NONE``: it should not); sets ``out.standstill``.
    ``share``: tracks shared with the last keyframe (taken at ``keyframe_time``)."""
    wheels_still = odom_motion is None or (
        odom_motion[0] < kc.standstill_distance_m and odom_motion[1] < kc.standstill_rotation_rad
    )
    # Parallax says "still" only over tracks the keyframe shares with this frame: with none left (every
    # track lost at once: a sudden occlusion, a light switched) it is undefined, not zero, and the loss
    # must make a keyframe, or the keyframe reference is never renewed and no keyframe follows for the
    # rest of a run without wheels.
    out.standstill = share.n_common >= MIN_COMMON_TRACKS and out.parallax_px < kc.standstill_parallax_px \
        and wheels_still
    if force:
        return KeyframeReason.LAST
    if out.standstill:
        return KeyframeReason.NONE
    if out.parallax_px >= parallax_threshold_px(kc, focal_px):
        return KeyframeReason.PARALLAX
    if share.tracked_ratio() < kc.min_tracked_ratio:
        return KeyframeReason.TRACK_LOSS
    if out.timestamp - keyframe_time >= kc.max_interval_s:
        return KeyframeReason.INTERVAL
    return KeyframeReason.NONE

def apply_gates(out: FrontendOutput, reason: KeyframeReason, gc: GateConfig) -> None:
    """Mark the frame a keyframe for ``reason`` and run the quality gates on it (``out.gate``, ``out.vision_ok``)."""
    if reason is KeyframeReason.FIRST:
        if len(out.track_ids) >= gc.min_features:
            out.is_keyframe, out.keyframe_reason = True, KeyframeReason.FIRST
            out.gate = GateOutcome.PASS
        else:
            out.gate = GateOutcome.FEW_FEATURES
        return
    if reason is KeyframeReason.NONE:
        return
    out.is_keyframe, out.keyframe_reason = True, reason
    # Quality gates on the candidate.
    if len(out.track_ids) < gc.min_features:
        out.gate, out.vision_ok = GateOutcome.FEW_FEATURES, False
    elif out.spread < gc.min_spread:
        out.gate, out.vision_ok = GateOutcome.POOR_SPREAD, False
    elif out.inlier_ratio < gc.min_inlier_ratio:
        out.gate, out.vision_ok = GateOutcome.LOW_INLIERS, False
    elif out.rot_comp_parallax_px < gc.min_parallax_px:
        # Rotation-only or tiny motion: existing landmarks still constrain the pose. The back end
        # still lets tracks whose own rays diverge enough (distant scenes, older tracks) become
        # landmarks; a pure spin gives none (each is checked for its triangulation angle).
        out.gate, out.vision_ok = GateOutcome.LOW_PARALLAX, True
    elif out.cheirality_ratio < gc.min_cheirality_ratio:
        out.gate, out.vision_ok = GateOutcome.CHEIRALITY, False
    else:
        out.gate = GateOutcome.PASS
