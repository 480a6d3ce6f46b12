"""Back end: the odometry factor's convention, accuracy on feature-level synthetic data, the window's blocks,
recovery, landmark bookkeeping (the factor builders are in test_factors.py)."""

import gtsam
import numpy as np
import pytest
from conftest import run_backend

from windowvo.backend import factors as fac
from windowvo.backend.smoother import SlidingWindowBackend, X
from windowvo.config import BackendConfig
from windowvo.geometry import make_T, rpy_to_R
from windowvo.synth.features import simulate_features
from windowvo.synth.generate import SynthSpec, WheelErrorModel, build_world, simulate_wheel_odometry
from windowvo.synth.paths import PathKind


@pytest.fixture(scope="module")
def long_features():
    spec = SynthSpec(path=PathKind.LOOP, duration_s=130.0, speed=0.8, seed=3,
                     wheel=WheelErrorModel(scale_error=0.01, yaw_bias_per_m=0.01))
    return simulate_features(spec, pixel_noise=0.5, outlier_ratio=0.05)


def test_feature_level_accuracy_beats_wheels(long_features):
    be, rep = run_backend(long_features, BackendConfig())
    _, wheel = run_backend(long_features, BackendConfig(), vision=False)
    assert rep.path_length_m >= 100.0
    assert rep.ate_se3_rmse_m <= 0.003 * rep.path_length_m, rep
    assert wheel.ate_se3_rmse_m >= 5.0 * rep.ate_se3_rmse_m, (wheel, rep)
    assert be.n_resets == 0
    # bounded window: only the window's poses remain in the smoother
    n_poses, n_keys = _poses_in_smoother(be)
    cfg = BackendConfig()
    assert cfg.window_keyframes <= n_poses <= cfg.window_keyframes + cfg.marginalize_every - 1
    assert n_keys - n_poses < 1500


def _poses_in_smoother(be) -> tuple[int, int]:
    keys = [gtsam.Symbol(k) for k in be.smoother.timestamps()]
    return sum(1 for s in keys if chr(s.chr()) == "x"), len(keys)


@pytest.mark.parametrize("block", [1, 5])
def test_old_keyframes_leave_the_window_in_blocks(block):
    """The smoother holds exactly the keyframes from window_start(k) to k: between window_keyframes
    and window_keyframes + block - 1 of them, and old ones leave only on every block-th keyframe."""
    spec = SynthSpec(path=PathKind.LOOP, duration_s=30.0, speed=0.8, seed=5)
    fs = simulate_features(spec, pixel_noise=0.5)
    cfg = BackendConfig(window_keyframes=8, marginalize_every=block)
    be = SlidingWindowBackend(fs.world.camera, cfg, use_odometry=True)
    sizes = []
    for i, fo in enumerate(fs.keyframes):
        odom = fs.odometry_step(i)
        be.add_keyframe(fo, odom)
        n_poses, _ = _poses_in_smoother(be)
        stamps = [t for k, t in be.smoother.timestamps().items() if chr(gtsam.Symbol(k).chr()) == "x"]
        assert min(stamps) == be.window_start() and n_poses == be.k - be.window_start() + 1, be.k
        sizes.append(n_poses)
    assert len(sizes) > 30 and be.n_resets == 0
    steady = sizes[cfg.window_keyframes + block:]
    assert min(steady) == 8 and max(steady) == 8 + block - 1
    # the oldest keyframe moves only when k is a multiple of the block
    drops = [k for k in range(1, len(sizes)) if sizes[k] < sizes[k - 1] + 1]
    assert drops and all(k % block == 0 for k in drops)


def test_odometry_between_factor_matches_ground_truth():
    spec = SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=20.0, seed=1,
                     wheel=WheelErrorModel(scale_error=0.0, yaw_bias_per_m=0.0, distance_noise=0.0, yaw_noise=0.0))
    world = build_world(spec)
    odo = simulate_wheel_odometry(world, spec.wheel, spec.seed, "synthetic")
    for t0, t1 in [(1.0, 1.5), (5.0, 5.6), (12.0, 12.3)]:
        T0, T1 = world.T_world_base(t0), world.T_world_base(t1)
        delta = odo.delta(t0, t1)
        f = gtsam.BetweenFactorPose3(X(0), X(1), gtsam.Pose3(delta), gtsam.noiseModel.Isotropic.Sigma(6, 0.01))
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose3(T0))
        v.insert(X(1), gtsam.Pose3(T1))
        err = f.unwhitenedError(v)
        assert np.abs(err).max() < 2e-3, err
        # and the factor measures something: a wrong pose gives a large residual
        v.update(X(1), gtsam.Pose3(T1 @ make_T(np.eye(3), [0.1, 0, 0])))
        assert np.abs(f.unwhitenedError(v)).max() > 0.05


class DegenerateOnce(SlidingWindowBackend):
    """Injects, at one keyframe, a landmark with a single projection factor (rank 2 for 3 unknowns)."""

    inject_at = 25
    injected = False

    def submit(self, graph, values, ts_map, remove):
        if self.k == self.inject_at and not self.injected:
            self.injected = True
            key = fac.L(10**9)  # a landmark key no track uses
            values.insert(key, gtsam.Point3(1.0, 2.0, 1.0))
            ts_map.insert((key, float(self.k)))
            graph.add(gtsam.GenericProjectionFactorCal3_S2(np.array([300.0, 200.0]), gtsam.noiseModel.Isotropic.Sigma(2, 1.0),
                                                           X(self.k), key, self.K, self.body_P_sensor))
        return super().submit(graph, values, ts_map, remove)


def test_recovers_from_an_injected_degenerate_update():
    spec = SynthSpec(path=PathKind.LOOP, duration_s=30.0, speed=0.8, seed=8)
    fs = simulate_features(spec)
    be, rep = run_backend(fs, BackendConfig(), backend_cls=DegenerateOnce)
    assert isinstance(be, DegenerateOnce) and be.injected
    assert be.n_resets == 1
    assert rep.ate_se3_rmse_m < 0.01 * rep.path_length_m


def test_batched_triangulation_recovers_points_and_applies_every_check():
    """Tracks of different lengths triangulated in one batch: exact points from noise-free pixels, the
    same answer as one track at a time (the padding does not leak), and each rejection rule."""
    from windowvo.backend.landmarks import triangulate_many
    from windowvo.camera import CameraModel

    cam = CameraModel(width=640, height=480, fx=340.0, fy=340.0, cx=320.0, cy=240.0)
    cfg = BackendConfig()
    cos_min = float(np.cos(np.radians(cfg.min_triangulation_angle_deg)))
    R_world_cam = rpy_to_R(-np.pi / 2, 0.0, -np.pi / 2)  # looking along world x
    cams = {k: (R_world_cam, np.array([0.0, 0.4 * k, 0.45])) for k in range(6)}  # sideways baseline

    def pixel(p_world, k):
        R, c = cams[k]
        pc = R.T @ (p_world - c)
        return np.array([cam.fx * pc[0] / pc[2] + cam.cx, cam.fy * pc[1] / pc[2] + cam.cy])

    rng = np.random.default_rng(2)
    pts = rng.uniform([3, -1, 0], [9, 3, 1.5], (12, 3))
    tracks = [[(k, pixel(p, k)) for k in range(i % 4 + 2)] for i, p in enumerate(pts)]
    far = np.array([70.0, 0.5, 0.5])
    tracks.append([(0, pixel(far, 0)), (1, pixel(far, 1))])  # rays closer than the minimum angle
    behind = [(k, pixel(pts[0], k)) for k in range(3)]
    behind[1] = (1, 2 * np.array([cam.cx, cam.cy]) - behind[1][1])  # a ray through the mirrored pixel
    tracks.append(behind)
    tracks.append([(0, pixel(pts[1], 0))])  # one observation
    bad = [(k, pixel(pts[2], k)) for k in range(4)]
    bad[2] = (2, bad[2][1] + [0.0, 8.0])  # one pixel 8 px off: reprojection check
    tracks.append(bad)
    out = triangulate_many(cam, cfg, tracks, cams, cos_min)
    for p_true, p in zip(pts, out[:12]):
        assert p is not None and np.allclose(p, p_true, atol=1e-9)
    assert out[12:] == [None, None, None, None]
    for tr, p in zip(tracks, out):
        alone = triangulate_many(cam, cfg, [tr], cams, cos_min)[0]
        assert (alone is None) == (p is None) and (p is None or np.array_equal(alone, p))


def test_landmark_budgets_count_only_landmarks_seen_recently():
    """Landmarks waiting for their block to be marginalised (not seen since ``seen_since``) leave
    their places in the budgets to new ones; floor and other landmarks have budgets of their own."""
    from windowvo.backend.landmarks import LandmarkManager, LandmarkState
    from windowvo.camera import CameraModel

    cam = CameraModel(width=640, height=480, fx=340.0, fy=340.0, cx=320.0, cy=240.0)
    lm = LandmarkManager(cam, BackendConfig(max_landmarks=10))
    for tid, (last_kf, floor) in enumerate([(3, False), (7, False), (8, False), (2, True), (9, True)]):
        lm.landmarks[tid] = LandmarkState(key=tid, last_kf=last_kf, on_ground=floor)
    assert lm.budgets(4) == (10 - 3, 4 - 2)  # every landmark counts
    assert lm.budgets(4, seen_since=5) == (10 - 2, 4 - 1)  # those last seen at 3 and 2 do not
    assert lm.budgets(4, seen_since=10) == (10, 4)


@pytest.mark.parametrize("budget_keyframes, expected", [(None, (10 - 3, 4 - 2)), (1, (10 - 1, 4 - 1)), (3, (10 - 2, 4 - 1))])
def test_landmark_budgets_follow_budget_keyframes(budget_keyframes, expected):
    """``backend.budget_keyframes``: a landmark holds its place in the budgets while one of the last N keyframes
    saw it (none: the window's keyframes, every landmark here)."""
    from windowvo.backend.landmark_factors import LandmarkFactors
    from windowvo.backend.landmarks import LandmarkManager, LandmarkState
    from windowvo.camera import CameraModel

    cam = CameraModel(width=640, height=480, fx=340.0, fy=340.0, cx=320.0, cy=240.0)
    cfg = BackendConfig(max_landmarks=10, window_keyframes=20, budget_keyframes=budget_keyframes,
                        min_landmarks_in_view=0)  # the budget alone (its top-up is the next test's)
    cfg.ground.max_landmarks = 4
    lm = LandmarkManager(cam, cfg)
    for tid, (last_kf, floor) in enumerate([(3, False), (7, False), (9, False), (2, True), (9, True)]):
        lm.landmarks[tid] = LandmarkState(key=tid, last_kf=last_kf, on_ground=floor)

    class Floor:
        use_ground = True
        use_odometry = True  # explicit settings: the same with or without wheels

    vision = LandmarkFactors.__new__(LandmarkFactors)
    vision.cfg, vision.lm, vision.floor = cfg, lm, Floor()
    assert vision._budgets(10) == expected


@pytest.mark.parametrize("minimum, expected", [(0, 10 - 12), (4, 4 - 1), (2, 2 - 1), (1, 0)])
def test_new_landmarks_are_admitted_while_few_are_in_view(minimum, expected):
    """``backend.min_landmarks_in_view``: a budget full of landmarks out of view (tracks that ended) still admits
    new ones up to that many seen by the previous keyframe (floor landmarks have their own budget)."""
    from windowvo.backend.landmarks import LandmarkManager, LandmarkState
    from windowvo.camera import CameraModel

    cam = CameraModel(width=640, height=480, fx=340.0, fy=340.0, cx=320.0, cy=240.0)
    lm = LandmarkManager(cam, BackendConfig(max_landmarks=10, min_landmarks_in_view=minimum))
    # Twelve others in the window (two over the budget), one of them seen by keyframe 9 (the previous one); a
    # floor landmark in view too, which does not count for the others.
    for tid, last_kf in enumerate([3, 4, 5, 6, 7, 8, 3, 4, 5, 6, 7, 9]):
        lm.landmarks[tid] = LandmarkState(key=tid, last_kf=last_kf, on_ground=False)
    lm.landmarks[12] = LandmarkState(key=12, last_kf=9, on_ground=True)
    assert lm.budgets(5, 0, 9) == (expected, 5 - 1)
    assert lm.budgets(5, 0) == (10 - 12, 5 - 1)  # without in_view_since: the budget alone


def test_factor_bookkeeping_knows_the_ground_factor_and_forgets_a_dropped_one():
    """Each landmark remembers its factors' smoother indices (removed with it as an outlier) and which one
    is its native ground factor (re-tied when the mount calibration switches); a dropped factor is
    forgotten, so a reused slot is never removed twice."""
    from windowvo.backend.landmarks import LandmarkManager, LandmarkState
    from windowvo.camera import CameraModel

    cam = CameraModel(width=640, height=480, fx=340.0, fy=340.0, cx=320.0, cy=240.0)
    lm = LandmarkManager(cam, BackendConfig())
    lm.landmarks[7] = LandmarkState(key=fac.L(7), last_kf=5, on_ground=True)
    lm.record_factors([None, (7, 4, False), (7, 5, False), (7, 5, True), (99, 5, False)], [10, 11, 12, 13, 14])
    st = lm.landmarks[7]
    assert st.factor_indices == [(4, 11), (5, 12), (5, 13)] and st.ground_factor == (5, 13)
    lm.drop_factor(7, 5, 13)
    assert st.factor_indices == [(4, 11), (5, 12)] and st.ground_factor is None
    lm.record_factors([(7, 5, True)], [13])  # the replacement, in the reused slot
    assert st.ground_factor == (5, 13) and st.factor_indices.count((5, 13)) == 1
    # floor landmarks have keys of their own symbol (their own relinearisation threshold)
    for tid, floor in ((8, True), (9, False)):
        lm.obs[tid] = [(3, np.zeros(2), 1.0), (4, np.ones(2), 1.0)]
        assert len(lm.promote(tid, 4, floor)) == 2
    assert lm.landmarks[8].key == fac.G(8) and lm.landmarks[9].key == fac.L(9)


def test_landmark_positions_come_from_the_last_estimate_and_only_for_live_landmarks():
    """Positions are read once per estimate; a forgotten landmark, one the estimate lacks, and (after a
    window restart) every old one are left out until the next estimate holds them."""
    from windowvo.backend.factors import L
    from windowvo.backend.landmarks import LandmarkManager, LandmarkState
    from windowvo.camera import CameraModel

    cam = CameraModel(width=640, height=480, fx=340.0, fy=340.0, cx=320.0, cy=240.0)
    lm = LandmarkManager(cam, BackendConfig())
    est = gtsam.Values()
    for tid in (4, 9, 12):
        lm.landmarks[tid] = LandmarkState(key=L(tid), last_kf=5)
        est.insert(L(tid), gtsam.Point3(tid, 0.0, 1.0))
    lm.landmarks[20] = LandmarkState(key=L(20), last_kf=5)  # not in the estimate (yet)
    lm.read_estimate(est)
    ids, pts = lm.positions()
    assert ids.tolist() == [4, 9, 12] and np.array_equal(pts[:, 0], [4.0, 9.0, 12.0])
    seen, p_seen, uv = lm.seen_now(np.array([9, 20, 33]), np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]), 5)
    assert seen == [9] and np.array_equal(p_seen, [[9.0, 0.0, 1.0]]) and np.array_equal(uv, [[1.0, 2.0]])
    lm.forget([9])
    assert lm.positions()[0].tolist() == [4, 12]
    lm.restart(6, np.array([4]), np.array([[1.0, 1.0]]))
    assert len(lm.positions()[0]) == 0  # nothing until the next estimate
    lm.landmarks[4] = LandmarkState(key=L(4), last_kf=6)
    assert len(lm.positions()[0]) == 0  # the old estimate's position of track 4 is not reused
    est2 = gtsam.Values()
    est2.insert(L(4), gtsam.Point3(0.5, 0.5, 2.0))
    lm.read_estimate(est2)
    ids, pts = lm.positions()
    assert ids.tolist() == [4] and np.array_equal(pts, [[0.5, 0.5, 2.0]])


@pytest.mark.parametrize("use_odometry", [True, False])
def test_auto_budget_and_two_view_guess_follow_the_wheels(use_odometry):
    """``budget_keyframes: auto`` and ``two_view_guess: auto`` (the defaults): without wheels the budget counts the
    landmarks the previous keyframe saw and a keyframe PnP cannot place starts from the two-view pose; with
    wheels both stay as before (the window's keyframes, constant velocity at a wheel gap)."""
    cfg = BackendConfig()
    assert cfg.budget_keyframes == "auto" and cfg.two_view_guess == "auto"
    assert cfg.budget_lag(use_odometry) == (cfg.window_keyframes if use_odometry else 1)
    assert cfg.uses_two_view_guess(use_odometry) is (not use_odometry)
    explicit = BackendConfig(budget_keyframes=3, two_view_guess=False)
    assert explicit.budget_lag(use_odometry) == 3 and explicit.uses_two_view_guess(use_odometry) is False
    assert BackendConfig(budget_keyframes=None).budget_lag(use_odometry) == cfg.window_keyframes
    with pytest.raises(ValueError):
        BackendConfig(budget_keyframes=0)


@pytest.mark.parametrize("two_view_guess", [True, False])
def test_a_keyframe_pnp_cannot_place_starts_from_the_two_view_pose(two_view_guess):
    """``backend.two_view_guess``: without wheels and with no landmark in view (no PnP), the initial guess of
    keyframe k is keyframe k-1 moved by the front end's relative pose (X_cur = R X_kf + t), its translation scaled
    to the constant-velocity step's length; with the option off, constant velocity (the last step's turn again)."""
    from windowvo.camera import CameraModel
    from windowvo.geometry import extrapolate_T, inv_T
    from windowvo.types import FrontendOutput

    cam = CameraModel(width=640, height=480, fx=340.0, fy=340.0, cx=320.0, cy=240.0)
    be = SlidingWindowBackend(cam, BackendConfig(two_view_guess=two_view_guess), use_odometry=False)
    T0 = np.eye(4)
    T1 = make_T(rpy_to_R(0.0, 0.0, 0.2), np.array([1.0, 0.1, 0.0]))  # the last step turned by 0.2 rad
    be.k = 2
    be.kf_pose[0], be.kf_pose[1] = T0, T1
    # What the images say since keyframe 1: straight on along the base's x axis, 0.05 rad of yaw to the right.
    T_kf_cur_base = make_T(rpy_to_R(0.0, 0.0, -0.05), np.array([1.0, 0.0, 0.0]))
    T_kf_cur_cam = inv_T(cam.T_base_cam) @ T_kf_cur_base @ cam.T_base_cam
    T_cur_kf = inv_T(T_kf_cur_cam)
    t = T_cur_kf[:3, 3]
    fo = FrontendOutput(frame_index=2, timestamp=0.2, track_ids=np.arange(0), pixels=np.zeros((0, 2)),
                        pixels_undistorted=np.zeros((0, 2)), track_ages=np.zeros(0), outlier_pixels=np.zeros((0, 2)),
                        R_cam_kf_cam=T_cur_kf[:3, :3], t_dir_kf=3.0 * t / np.linalg.norm(t))
    T_guess = be._initial_guess(fo, None)
    T_cv = extrapolate_T(T0, T1)
    if not two_view_guess:
        assert np.allclose(T_guess, T_cv)
        return
    step = float(np.linalg.norm(T_cv[:3, 3] - T1[:3, 3]))
    expected = T1 @ make_T(T_kf_cur_base[:3, :3], T_kf_cur_base[:3, 3] * step)
    assert np.allclose(T_guess, expected, atol=1e-9)
