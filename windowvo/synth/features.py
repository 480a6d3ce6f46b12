"""Feature-level simulation: the renderer's world, but observations instead of images.

Landmarks are scattered on the scene's surfaces and projected into keyframes with pixel
noise and a share of gross outliers; each visible run of a landmark becomes a track with
an id. The output replaces the front end end-to-end, so the back end can be tested fast
and with exact data association.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import inv_T
from ..io.odometry import WheelOdometry
from ..types import FrontendOutput, GateOutcome, KeyframeReason
from .generate import SyntheticWorld, SynthSpec, build_world, simulate_wheel_odometry


@dataclass
class FeatureSequence:
    world: SyntheticWorld
    keyframes: list[FrontendOutput]
    gt_T_world_base: list[np.ndarray]  # per keyframe
    odometry: WheelOdometry
    p_world_landmarks: np.ndarray


def sample_landmarks(world: SyntheticWorld, n: int, rng: np.random.Generator) -> np.ndarray:
    planes = world.scene.planes
    areas = np.array([p.length_u * p.length_v for p in planes])
    idx = rng.choice(len(planes), size=n, p=areas / areas.sum())
    pts = []
    for i in idx:
        p = planes[i]
        u, v = rng.uniform(0, p.length_u), rng.uniform(0, p.length_v)
        pts.append(p.origin + u * p.axis_u + v * p.axis_v + 0.01 * p.normal)
    return np.asarray(pts)


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
    # Keyframe times: every keyframe_spacing_m of true travel.
    ts = np.arange(0.0, world.planar.duration, 0.05)
    xy = np.stack(world.planar.at(ts)[:2], axis=1)
    dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    kf_times = [ts[0]]
    last = 0.0
    for t, d in zip(ts, dist):
        if d - last >= keyframe_spacing_m:
            kf_times.append(t)
            last = d
    track_of = -np.ones(n_landmarks, np.int64)  # current track id of each landmark
    next_track = 0
    kfs: list[FrontendOutput] = []
    gts: list[np.ndarray] = []
    for t in kf_times:
        T_wb = world.T_world_base(t)
        T_cw = inv_T(T_wb @ cam.T_base_cam)
        pc = P @ T_cw[:3, :3].T + T_cw[:3, 3]
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
                track_of[j] = next_track
                next_track += 1
        meas = uv[idx] + rng.normal(0, pixel_noise, (len(idx), 2))
        out_mask = rng.random(len(idx)) < outlier_ratio
        meas[out_mask] = rng.uniform([0, 0], [cam.width, cam.height], (int(out_mask.sum()), 2))
        und = cam.undistort_pixels(meas) if cam.has_distortion else meas
        fo = FrontendOutput(
            frame_index=len(kfs),
            timestamp=float(t),
            track_ids=track_of[idx].copy(),
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
