"""Metric-scale pieces on their own: floor detection and attitude, the floor model's floor after a scale
drift, the wheel calibration and its key lifecycle (the factor builders are in test_factors.py)."""

import gtsam
import numpy as np
import pytest

from windowvo.backend import factors as fac
from windowvo.backend.factors import L, X
from windowvo.backend.ground import (
    FloorAttitude,
    attitude_jitter_deg,
    beside_track,
    fit_floor_plane,
    floor_mask,
    level_up,
    levelled_mount,
    normal_from_tilt_deg,
    off_floor,
    tilt_significant,
)
from windowvo.backend.smoother import SlidingWindowBackend
from windowvo.config import BackendConfig, GroundConfig
from windowvo.geometry import make_T, rot_x, rotation_angle, rpy_to_R
from windowvo.synth.features import simulate_features
from windowvo.synth.generate import SynthSpec, WheelErrorModel, camera_for
from windowvo.synth.paths import PathKind
from windowvo.types import OdometryStep, WheelCalibration


def test_floor_attitude_is_the_median_of_the_fits():
    """A mount pitched by 1 deg: noisy fits around the tilted normal, a few off by a ramp's 8 deg; the
    learnt normal is within 0.1 deg of the truth, ready only from min_fits on, and forgets beyond max_fits."""
    rng = np.random.default_rng(6)
    truth = rpy_to_R(0.0, np.radians(1.0), 0.0)[:, 2]
    fa = FloorAttitude(min_fits=10, max_fits=60)
    assert not fa.ready and np.allclose(fa.normal, [0, 0, 1])
    for i in range(60):
        pitch = 8.0 if i % 10 == 3 else 1.0 + rng.normal(0, 0.3)
        fa.add(rpy_to_R(np.radians(rng.normal(0, 0.3)), np.radians(pitch), 0.0)[:, 2])
        assert fa.ready == (i + 1 >= 10)
    assert np.degrees(np.arccos(np.clip(fa.normal @ truth, -1, 1))) < 0.1
    tx, ty = fa.tilt_deg()
    assert tx == pytest.approx(1.0, abs=0.1) and abs(ty) < 0.1
    assert np.allclose(normal_from_tilt_deg(tx, ty), fa.normal, atol=1e-12)  # the summary's way back
    # standard error of the median: 1.25 * hypot(0.3, 0.3) / sqrt(60) = 0.07 deg, the ramp's fits aside
    assert 0.04 < fa.standard_error_deg() < 0.11
    assert FloorAttitude(1, 10).standard_error_deg() == float("inf")
    assert fa.significant()  # 1 deg, 0.07 deg standard error: the mount is off
    for _ in range(60):  # the mount was corrected: the old fits leave
        fa.add(np.array([0.0, 0.0, 1.0]))
    assert np.allclose(fa.normal, [0, 0, 1]) and not fa.significant()
    # not significant: below 0.3 deg, or within three standard errors, or before min_fits
    assert not tilt_significant(0.25, 0.01) and not tilt_significant(0.6, 0.25) and tilt_significant(0.6, 0.15)
    few = FloorAttitude(min_fits=10, max_fits=60)
    for _ in range(9):
        few.add(rpy_to_R(0.0, np.radians(2.0), 0.0)[:, 2])
    assert not few.significant()


def _step(azimuth_deg: float, climb_deg: float) -> np.ndarray:
    """A unit step in the base frame: heading ``azimuth_deg`` from +x, climbing by ``climb_deg``."""
    a, e = np.radians(azimuth_deg), np.radians(climb_deg)
    return np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])


def test_the_floor_tilt_from_the_motion_is_the_climb_of_the_steps():
    """``ground.mount_from_motion``: a camera pitched 1 deg down against its T_base_cam sees the base's steps along
    the floor climb by 1 deg in the set-up's base frame, forward and reversing alike; the learnt tilt toward +x is
    -1 deg (the floor's normal perpendicular to the steps), the roll stays the plane fits', steps far off the x
    axis are left out, and a level base's noisy steps are not significant."""
    rng = np.random.default_rng(3)
    fa = FloorAttitude(min_fits=10, max_fits=60, from_motion=True)
    for i in range(40):
        sign = -1.0 if i % 4 == 0 else 1.0  # every fourth step reversing
        d = sign * _step(rng.normal(0.0, 5.0), 1.0 + rng.normal(0.0, 0.1))
        assert fa.add_motion(d)
        assert fa.ready == (i + 1 >= 10)
    assert not fa.add_motion(_step(60.0, 5.0)) and not fa.add_motion(_step(120.0, 5.0))  # turns: left out
    tx, ty = fa.tilt_deg()
    assert tx == pytest.approx(-1.0, abs=0.05) and ty == 0.0, (tx, ty)
    assert np.allclose(fa.normal @ _step(0.0, 1.0), 0.0, atol=1e-3)  # perpendicular to the steps
    assert fa.standard_error_deg() < 0.05 and fa.significant()
    for _ in range(10):  # plane fits rolled by 0.8 deg give the roll, not the pitch
        fa.add(rpy_to_R(np.radians(0.8), np.radians(3.0), 0.0)[:, 2])
    tx, ty = fa.tilt_deg()
    assert tx == pytest.approx(-1.0, abs=0.05) and ty == pytest.approx(-0.8, abs=0.01), (tx, ty)
    level = FloorAttitude(min_fits=10, max_fits=60, from_motion=True)
    for _ in range(40):
        level.add_motion(_step(rng.normal(0.0, 5.0), rng.normal(0.0, 0.2)))
    assert abs(level.tilt_deg()[0]) < 0.1 and not level.significant()
    rocking = FloorAttitude(min_fits=10, max_fits=60, from_motion=True)  # the pitch changes: not a mount error
    for i in range(40):
        rocking.add_motion(_step(0.0, 0.0 if i < 20 else 1.5))
    assert not rocking.significant()
    off = FloorAttitude(min_fits=10, max_fits=60)  # the option off: steps change nothing
    for _ in range(20):
        off.add_motion(_step(0.0, 1.0))
    assert not off.ready and np.allclose(off.normal, [0, 0, 1])


def _tilted_z(roll_deg: np.ndarray, pitch_deg: np.ndarray) -> np.ndarray:
    return np.array([rpy_to_R(np.radians(r), np.radians(p), 0.0)[:, 2] for r, p in zip(roll_deg, pitch_deg)])


def test_attitude_jitter_tells_a_rocking_base_from_a_level_one_and_a_ramp():
    rng = np.random.default_rng(4)
    n = 25
    level = _tilted_z(rng.normal(0, 0.005, n), rng.normal(0, 0.005, n))
    # a ramp: level, then the pitch turns by 7.6 deg over three keyframes, then stays
    ramp = _tilted_z(np.zeros(n), np.clip((np.arange(n) - 10) * 7.6 / 3, 0, 7.6))
    rocking = _tilted_z(rng.normal(0, 1.0, n), rng.normal(0, 1.0, n))
    assert attitude_jitter_deg(level) < 0.02
    assert attitude_jitter_deg(ramp) < 0.02  # the median ignores the few keyframes of the turn
    assert 0.8 < attitude_jitter_deg(rocking) < 2.5
    assert attitude_jitter_deg(level[:1]) == 0.0


def test_level_up_averages_the_rocking_out_and_keeps_another_plane_out():
    rng = np.random.default_rng(5)
    floor = rpy_to_R(0.0, np.radians(3.0), 0.0)[:, 2]  # a floor sloping by 3 deg
    # a window: 20 keyframes rocking by 0.7 deg on it, 8 still on the level floor before the slope
    # (their plain mean is 0.83-1.1 deg off the slope over ten seeds)
    on_slope = _tilted_z(rng.normal(0, 0.7, 20), 3.0 + rng.normal(0, 0.7, 20))
    before = _tilted_z(np.zeros(8), np.zeros(8))
    fitted = rpy_to_R(0.0, np.radians(3.4), 0.0)[:, 2]  # the fitted normal: noisy, 0.4 deg off
    up = level_up(np.concatenate([before, on_slope]), fitted, 2.0)
    assert np.degrees(np.arccos(np.clip(up @ floor, -1, 1))) < 0.4
    assert np.linalg.norm(up) == pytest.approx(1.0)
    # no keyframe near the fitted normal: the fitted normal itself
    assert np.allclose(level_up(before, fitted, 2.0), fitted)


def _scene_points(rng, n_floor=80, ramp=False):
    """Points in a base frame with the camera at (0.25, 0, 0.45): floor, a wall and a box top."""
    x = rng.uniform(0.6, 5.0, n_floor)
    y = rng.uniform(-2.0, 2.0, n_floor)
    z = np.where(ramp & (x > 2.5), (x - 2.5) * np.tan(np.radians(15)), 0.0) + rng.normal(0, 0.004, n_floor)
    floor = np.stack([x, y, z], axis=1)
    wall = np.stack([np.full(40, 6.0), rng.uniform(-3, 3, 40), rng.uniform(0.0, 2.5, 40)], axis=1)
    box_top = np.stack([rng.uniform(2.0, 2.6, 15), rng.uniform(-0.5, 0.5, 15), np.full(15, 0.3)], axis=1)
    return floor, np.concatenate([floor, wall, box_top])


def test_floor_detection_finds_the_floor_and_nothing_else():
    rng = np.random.default_rng(0)
    floor, pts = _scene_points(rng)
    T_base_cam = make_T(np.eye(3), [0.25, 0.0, 0.45])
    T_world_base = make_T(rpy_to_R(0, 0, 0.8), [3.0, -1.0, 0.0])
    p_world = pts @ T_world_base[:3, :3].T + T_world_base[:3, 3]
    mask, fit = floor_mask(p_world, T_world_base, T_base_cam, 0.45, GroundConfig(), rng)
    assert fit is not None and fit.tilt_deg < 1.0 and fit.camera_height_m == pytest.approx(0.45, abs=0.01)
    n = len(floor)
    assert mask[n:].sum() == 0  # no wall or box point
    # floor points within range and below the horizon by 8 deg are found (the far ones are not candidates)
    near = np.degrees(np.arctan2(0.45, np.hypot(floor[:, 0] - 0.25, floor[:, 1]))) >= 8.5
    assert mask[:n][near].mean() > 0.95


def test_floor_detection_switches_off_where_the_floor_assumption_breaks():
    rng = np.random.default_rng(1)
    T_base_cam = make_T(np.eye(3), [0.25, 0.0, 0.45])
    floor, pts = _scene_points(rng)
    # the estimate's scale is 40 % off (distances from the camera 1.4x too long): the plane is not at the
    # camera's height, so no floor
    cam = T_base_cam[:3, 3]
    mask, fit = floor_mask(cam + 1.4 * (pts - cam), np.eye(4), T_base_cam, 0.45, GroundConfig(), rng)
    assert fit is None and not mask.any()
    # a featureless floor: too few points
    mask, fit = floor_mask(pts[-60:], np.eye(4), T_base_cam, 0.45, GroundConfig(), rng)
    assert fit is None
    # a ramp ahead: only the flat part is floor
    floor, pts = _scene_points(rng, ramp=True)
    mask, fit = floor_mask(pts, np.eye(4), T_base_cam, 0.45, GroundConfig(), rng)
    on_ramp = floor[:, 0] > 2.8
    assert fit is not None and not mask[: len(floor)][on_ramp].any()
    # a camera that sees no floor
    assert fit_floor_plane(np.zeros((0, 3)), np.zeros(3), 0.45, GroundConfig(), rng) is None


def test_beside_track_judges_points_the_base_has_passed():
    # the base drove along x from 0 to 4 m, then turned left onto y (a corner of a loop)
    track = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0, 0.0, 0.0], [4.0, 2.0, 0.0]])
    pts = np.array([
        [1.0, 0.3, 0.0],  # on the track's corridor
        [1.0, -0.9, 0.02],  # a mat beside the first straight
        [3.0, 1.2, 0.0],  # inside the corner: 1 m from the second straight, 1.2 m from the first
        [3.5, 0.5, 0.0],  # near the corner, on the corridor
        [4.0, 5.0, 0.0],  # ahead of the newest keyframe: not judged yet
        [4.9, 2.8, 0.0],  # ahead and beside: not judged yet either
        [-1.0, 3.0, 0.0],  # behind the oldest keyframe: no track beside it in the window
    ])
    beside = beside_track(pts, track, 0.6)
    assert beside.tolist() == [False, True, True, False, False, False, False]
    assert not beside_track(pts, track, 1.5).any()  # a wider corridor keeps them all
    assert not beside_track(pts, track[:1], 0.6).any()  # one keyframe is no track
    assert beside_track(np.zeros((0, 3)), track, 0.6).shape == (0,)
    # a base that stopped: its standing keyframes add no segment, and a point ahead is still not judged, also
    # when the estimate's positions jitter by millimetres while it stands
    stopped = np.r_[track, np.repeat(track[-1:], 4, axis=0)]
    assert beside_track(pts, stopped, 0.6).tolist() == beside.tolist()
    rng = np.random.default_rng(5)
    straight = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    ahead = np.array([[4.0, 0.0, 0.0], [3.0, 1.0, 0.0]])
    for _ in range(200):
        jittered = np.r_[straight, straight[-1] + rng.normal(0.0, 0.002, (4, 3))]
        assert not beside_track(ahead, jittered, 0.6).any()


def test_off_floor_unties_a_raised_surface_and_little_else():
    rng = np.random.default_rng(7)
    floor = rng.normal(0.0, 0.004, 80)
    kerb = 0.03 + rng.normal(0.0, 0.004, 20)  # a fifth of the tied points on a surface 3 cm up
    off = off_floor(np.concatenate([floor, kerb]), 2.5, 0.001)
    assert off[80:].mean() >= 0.9 and off[:80].mean() <= 0.05
    # ... and then on both sides (the floor's height is not biased by cutting one tail of its noise)
    off = off_floor(np.concatenate([floor, kerb, [-0.03, -0.035]]), 2.5, 0.001)
    assert off[-2:].all()
    # a plain floor: its tails are its own noise, nothing is untied
    assert not off_floor(rng.normal(0.0, 0.004, 400), 2.5, 0.001).any()
    # a lower surface (a drain) is not a raised one: nothing is untied either
    assert not off_floor(np.concatenate([floor, -kerb]), 2.5, 0.001).any()
    # the robust sigma has a floor: near-perfect heights untie nothing a millimetre off
    assert not off_floor(np.r_[np.zeros(30), 0.001], 2.5, 0.002).any()
    assert not off_floor(np.array([0.0] * 5 + [0.5]), 2.5, 0.001).any()  # too few points to judge


def test_floor_points_at_the_base_origin_are_not_candidates():
    """A camera mounted behind the base origin sees the floor at the origin, where the ground factor's
    bearing from the base origin is undefined: such points are left out, and every candidate makes a factor."""
    from windowvo.backend.ground import floor_candidates

    cam = np.array([-0.6, 0.0, 0.45])  # 0.6 m behind the base origin
    pts = np.array([[0.0, 0.0, 0.0], [0.05, 0.02, 0.0], [1.0, 0.3, 0.0], [2.0, -0.4, 0.0]])
    mask = floor_candidates(pts, cam, 0.45, GroundConfig())
    assert mask.tolist() == [False, False, True, True]
    for p in pts[mask]:
        fac.ground_factor(X(1), L(7), p, 0.0, 0.0135, BackendConfig())  # no error


def _drifted_floor_of(be: SlidingWindowBackend, scale: float, rng: np.random.Generator):
    """``FloorModel.floor_of`` for new landmarks on the floor, a wall and a box, seen at ``scale`` x their true
    distances from the camera (the estimate's scale drifted), with no landmarks in the window."""
    cam = be.T_base_cam[:3, 3]
    floor, pts = _scene_points(rng)
    born = [(i, cam + scale * (p - cam)) for i, p in enumerate(pts)]
    mask, fit = be.floor.floor_of(be.k, born, np.eye(4))
    return mask, fit, len(floor)


@pytest.mark.parametrize("use_odometry,reanchor", [(False, True), (True, True), (False, False)])
def test_a_monocular_run_takes_the_floor_back_after_its_scale_drifted(use_odometry, reanchor):
    """Without wheels the floor is the only scale source: a floor plane at the same wrong height at two
    consecutive keyframes is the floor seen at a drifted scale, and is taken back (its ground factors then
    pull the scale back); two planes that disagree are not (one could be a table top). With wheels the
    scale is theirs: a plane at the wrong height is never floor; nor without them when the re-anchoring is
    switched off (``ground.reanchor_drifted_floor``)."""
    spec = SynthSpec(path=PathKind.LOOP, duration_s=2.0, seed=1)
    cfg = BackendConfig()
    cfg.ground.reanchor_drifted_floor = reanchor
    be = SlidingWindowBackend(camera_for(spec), cfg, use_odometry=use_odometry)
    takes_back = reanchor and not use_odometry
    be.metric = True  # as after the monocular start
    rng = np.random.default_rng(3)
    mask, fit, n_floor = _drifted_floor_of(be, 1.0, rng)  # the right scale: the floor, either way
    assert fit is not None and mask[:n_floor].mean() > 0.5 and not mask[n_floor:].any()
    for scale, taken in ((0.65, False), (1.9, False), (1.9, takes_back), (1.85, takes_back)):
        mask, fit, n_floor = _drifted_floor_of(be, scale, rng)
        assert (fit is not None) == taken, scale
        if taken:
            assert fit.camera_height_m == pytest.approx(scale * 0.45, rel=0.05)
            assert mask[:n_floor].mean() > 0.5 and not mask[n_floor:].any()
        else:
            assert not mask.any()
    assert be.n_scale_reanchors == (2 if takes_back else 0)


def test_wheel_calibration_correct_removes_scale_and_bias():
    T_true = make_T(rpy_to_R(0, 0, 0.1), [0.5, 0.02, 0.0])
    d = float(np.hypot(0.5, 0.02))
    meas = make_T(rpy_to_R(0, 0, 0.1 + 0.01 * d), [0.5 * 1.03, 0.02 * 1.03, 0.0])
    assert np.allclose(WheelCalibration(1.03, 0.01).correct(meas, d), T_true, atol=1e-9)


@pytest.mark.parametrize("block", [1, 4])
def test_calibration_states_survive_odometry_gaps_and_marginalisation(block):
    """A calibration state joins with every block of keyframes that leaves the window together (random
    walk from the previous one), with or without a wheel reading, so odometry gaps and the fixed lag
    never leave a key without factors (the GTSAM fixed-lag traps)."""
    spec = SynthSpec(path=PathKind.LOOP, duration_s=40.0, speed=0.8, seed=4,
                     wheel=WheelErrorModel(scale_error=0.02, yaw_bias_per_m=0.01))
    fs = simulate_features(spec)
    cfg = BackendConfig(window_keyframes=8, marginalize_every=block)
    be = SlidingWindowBackend(fs.world.camera, cfg, use_odometry=True)
    for i, fo in enumerate(fs.keyframes):
        odom = None
        if i > 0:
            t0, t1 = fs.keyframes[i - 1].timestamp, fo.timestamp
            odom = OdometryStep(fs.odometry.delta(t0, t1), fs.odometry.distance(t0, t1), ok=not (20 <= i < 24))
        be.add_keyframe(fo, odom)
    assert be.n_resets == 0
    keys = [gtsam.Symbol(k) for k in be.smoother.timestamps()]
    n_cal = sum(1 for s in keys if chr(s.chr()) == "c")
    # one per block of keyframes in the window (the window starts at a block), older ones marginalised
    n_kf = be.k - be.window_start() + 1
    assert 8 <= n_kf <= 8 + block - 1
    assert n_cal == -(-n_kf // block)
    cal = be.calibration_with_sigma()
    # Vision sees rotation, so the wheels' heading error is observable even without a metric floor cue. On a loop
    # that turns one way at a steady curvature it is one number per metre, the yaw bias plus (yaw scale - 1) times
    # the curvature, which the two states share by their priors: that sum is what the wheels got wrong (0.01 rad/m).
    T = np.stack(fs.gt_T_world_base)
    yaw = np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    curvature = (yaw[-1] - yaw[0]) / np.hypot(*np.diff(T[:, :2, 3], axis=0).T).sum()
    assert 0.15 < curvature < 0.3  # the loop this test was written for (0.22 rad/m)
    assert cal.yaw_bias_per_m + (cal.yaw_scale - 1.0) * curvature == pytest.approx(0.01, abs=0.003)
    assert 0 < cal.yaw_bias_sigma < 0.01


def test_levelled_mount_undoes_a_pitched_calibration():
    """A calibration that claims the camera pitched 1 deg further down than it is: the floor's normal seen
    through it, in the claimed base frame, gives back the true T_base_cam (a pitch error turns the camera
    about its horizontal x axis, the smallest rotation that levels the floor)."""
    R_fwd = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera z forward, x right
    T_true = make_T(R_fwd @ rot_x(-np.radians(12.0)), [0.25, 0.0, 0.45])
    T_claimed = make_T(R_fwd @ rot_x(-np.radians(13.0)), [0.25, 0.0, 0.45])
    n_seen = T_claimed[:3, :3] @ T_true[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the floor's z, as the claim sees it
    assert np.degrees(np.arccos(n_seen[2])) == pytest.approx(1.0, abs=1e-9)
    T_fixed = levelled_mount(T_claimed, n_seen)
    assert rotation_angle(T_fixed[:3, :3].T @ T_true[:3, :3]) < 1e-9
    assert np.allclose(T_fixed[:3, 3], T_true[:3, 3])
    assert np.allclose(levelled_mount(T_true, [0.0, 0.0, 1.0]), T_true)  # a level floor changes nothing



def test_camera_height_up_to_scale_is_in_the_points_unit():
    """Floor points around the camera centre, in an arbitrary unit (the camera 2.7 units above the floor):
    the height comes back in that unit, with and without the refining second fit; no floor, None."""
    from windowvo.backend.ground import camera_height_up_to_scale

    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(3.0, 25.0, 200), rng.uniform(-6.0, 6.0, 200)])
    floor = np.column_stack([xy, np.full(200, -2.7) + rng.normal(0.0, 0.01, 200)])
    for refine in (False, True):
        h = camera_height_up_to_scale(floor, GroundConfig(), np.random.default_rng(0), refine=refine)
        assert h == pytest.approx(2.7, rel=0.01)
    wall = np.column_stack([np.full(200, 8.0), xy[:, 1], rng.uniform(-2.0, 2.0, 200)])
    assert camera_height_up_to_scale(wall, GroundConfig(), np.random.default_rng(0)) is None
