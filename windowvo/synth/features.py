"""Feature-level simulation: the renderer's world, but observations instead of images.

Landmarks are scattered on the scene's surfaces and projected into keyframes with pixel
noise and a share of gross outliers; each visible run of a landmark becomes a track with
an id. The output replaces the front end end-to-end, so the back end can be tested fast
and with exact data association.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io.odometry import WheelOdometry
from ..types import FrontendOutput, GateOutcome, KeyframeReason, OdometryStep
from . import exact
from .exact import inv_T
from .generate import SyntheticWorld, SynthSpec, build_world, simulate_wheel_odometry


@dataclass
class FeatureSequence:
    world: SyntheticWorld
    keyframes: list[FrontendOutput]
    gt_T_world_base: list[np.ndarray]  # per keyframe
    odometry: WheelOdometry
    p_world_landmarks: np.ndarray

    def odometry_step(self, i: int) -> OdometryStep | None:
        """The simulated wheels' step from keyframe i - 1 to keyframe i (None for the first keyframe)."""
        if i == 0:
            return None
        t0, t1 = self.keyframes[i - 1].timestamp, self.keyframes[i].timestamp
        return OdometryStep(self.odometry.delta(t0, t1), self.odometry.distance(t0, t1))


def sample_landmarks(world: SyntheticWorld, n: int, rng: np.random.Generator) -> np.ndarray:
    planes = world.scene.planes
    areas = np.array([p.length_u * p.length_v for p in planes])
    idx = rng.choice(len(planes), size=n, p=areas / areas.sum())
    pts = []
    for i in idx:
        p = planes[i]
        u, v = rng.uniform(0, p.length_u), rng.uniform(0, p.length_v)
        pts.append(p.origin + u * p.axis_u + v * p.axis_v)
    return np.asarray(pts)


def keyframe_times(world: SyntheticWorld, spacing_m: float) -> list[float]:
    """Keyframe times: every ``spacing_m`` of true travel."""
    ts = np.arange(0.0, world.planar.duration, 0.05)
    xy = np.stack(world.planar.at(ts)[:2], axis=1)
    dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    kf_times = [ts[0]]
    last = 0.0
    for t, d in zip(ts, dist):
        if d - last >= spacing_m:
            kf_times.append(t)
            last = d
    return kf_times


@dataclass
class _Tracks:
    """Which landmark is on which track (-1: none) and the next track id."""

    track_of: np.ndarray
    next_track: int = 0


def _observe(world: SyntheticWorld, P: np.ndarray, T_wb: np.ndarray, tracks: _Tracks, rng: np.random.Generator,
             max_range_m: float, max_per_frame: int, pixel_noise: float, outlier_ratio: float):
    """Landmarks seen from ``T_wb``: their indices and noisy pixels (a share replaced by outliers)."""
    cam = world.camera
    n_landmarks = len(P)
    track_of = tracks.track_of
    T_cw = inv_T(exact.matmul(T_wb, cam.T_base_cam))
    pc = exact.matmul(P, T_cw[:3, :3].T) + T_cw[:3, 3]
    vis = (pc[:, 2] > 0.3) & (np.linalg.norm(pc, axis=1) < max_range_m)
    uv = np.zeros((n_landmarks, 2))
    uv[vis] = cam.project(pc[vis])
    vis &= cam.in_image(uv, margin=5)
    # Only surfaces facing the camera are seen (a cheap occlusion model).
    idx = np.nonzero(vis)[0]
    if len(idx) > max_per_frame:
        # prefer continuing tracks, like a tracker would
        cont = idx[track_of[idx] >= 0]
        new = idx[track_of[idx] < 0]
        rng.shuffle(new)
        idx = np.concatenate([cont[:max_per_frame], new[: max(0, max_per_frame - len(cont))]])
    seen = np.zeros(n_landmarks, bool)
    seen[idx] = True
    track_of[~seen] = -1  # a landmark that left the view starts a new track when it returns
    for j in idx:
        if track_of[j] < 0:
            track_of[j] = tracks.next_track
            tracks.next_track += 1
    meas = uv[idx] + rng.normal(0, pixel_noise, (len(idx), 2))
    out_mask = rng.random(len(idx)) < outlier_ratio
    meas[out_mask] = rng.uniform([0, 0], [cam.width, cam.height], (int(out_mask.sum()), 2))
    return idx, meas


def simulate_features(
    spec: SynthSpec,
    keyframe_spacing_m: float = 0.4,
    n_landmarks: int = 6000,
    pixel_noise: float = 0.5,
    outlier_ratio: float = 0.05,
    max_range_m: float = 12.0,
    max_per_frame: int = 150,
) -> FeatureSequence:
    world = build_world(spec)
    rng = np.random.default_rng(spec.seed + 17)
    cam = world.camera
    P = sample_landmarks(world, n_landmarks, rng)
    odo = simulate_wheel_odometry(world, spec.wheel, spec.seed, "synthetic")
    tracks = _Tracks(-np.ones(n_landmarks, np.int64))  # current track id of each landmark
    kfs: list[FrontendOutput] = []
    gts: list[np.ndarray] = []
    for t in keyframe_times(world, keyframe_spacing_m):
        T_wb = world.T_world_base(t)
        idx, meas = _observe(world, P, T_wb, tracks, rng, max_range_m, max_per_frame, pixel_noise, outlier_ratio)
        und = cam.undistort_pixels(meas) if cam.has_distortion else meas
        fo = FrontendOutput(
            frame_index=len(kfs),
            timestamp=float(t),
            track_ids=tracks.track_of[idx].copy(),
            pixels=meas,
            pixels_undistorted=und,
            track_ages=np.zeros(len(idx), np.int32),
            outlier_pixels=np.zeros((0, 2)),
            is_keyframe=True,
            keyframe_reason=KeyframeReason.PARALLAX if kfs else KeyframeReason.FIRST,
            gate=GateOutcome.PASS,
        )
        kfs.append(fo)
        gts.append(T_wb)
    return FeatureSequence(world, kfs, gts, odo, P)
