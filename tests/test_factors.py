"""The factor builders (``windowvo/backend/factors.py``) on their own: robust thresholds, the calibrated
wheel factor, the ground factors (native, level, along a learnt normal; residuals and Jacobians against
numerical derivatives), the planar attitude prior, and the relinearisation thresholds of every state kind."""

import gtsam
import numpy as np
import pytest

from windowvo.backend import factors as fac
from windowvo.backend.factors import C, L, X
from windowvo.config import BackendConfig
from windowvo.geometry import R_to_rpy, make_T, rpy_to_R


def test_robust_thresholds_are_chi_square_quantiles():
    # Known quantiles of the chi-square distribution at 95 %: 3.841 (1 dof), 5.991 (2), 7.815 (3).
    assert fac.robust_threshold(1, 0.95) == pytest.approx(np.sqrt(3.8415), abs=1e-3)
    assert fac.robust_threshold(2, 0.95) == pytest.approx(np.sqrt(5.9915), abs=1e-3)
    assert fac.robust_threshold(3, 0.95) == pytest.approx(np.sqrt(7.8147), abs=1e-3)
    cfg = BackendConfig()
    assert fac.threshold(None, 2, cfg) == pytest.approx(2.4477, abs=1e-3)
    assert fac.threshold(1.345, 2, cfg) == 1.345  # an explicit threshold wins


def test_robust_thresholds_match_the_chi_square_closed_forms():
    import math

    for conf in (0.5, 0.9, 0.95, 0.99, 0.999):
        x1, x2, x3 = (fac.robust_threshold(d, conf) ** 2 for d in (1, 2, 3))
        assert math.erf(math.sqrt(x1 / 2)) == pytest.approx(conf, abs=1e-12)
        assert 1 - math.exp(-x2 / 2) == pytest.approx(conf, abs=1e-12)
        closed3 = math.erf(math.sqrt(x3 / 2)) - math.sqrt(2 * x3 / math.pi) * math.exp(-x3 / 2)
        assert closed3 == pytest.approx(conf, abs=1e-12)


def _numerical_jacobians(factor, values: gtsam.Values, eps: float = 1e-6) -> list[np.ndarray]:
    out = []
    for key in list(factor.keys()):
        dims = 6 if values.exists(key) and key in (X(0), X(1)) else None
        if dims is None:
            dims = 3
        cols = []
        for i in range(dims):
            d = np.zeros(dims)
            d[i] = eps
            vp, vm = gtsam.Values(values), gtsam.Values(values)
            if dims == 6:
                vp.update(key, values.atPose3(key).retract(d))
                vm.update(key, values.atPose3(key).retract(-d))
            else:
                vp.update(key, values.atPoint3(key) + d)
                vm.update(key, values.atPoint3(key) - d)
            cols.append((factor.unwhitenedError(vp) - factor.unwhitenedError(vm)) / (2 * eps))
        out.append(np.stack(cols, axis=1))
    return out


def _analytic_jacobians(factor, values: gtsam.Values) -> list[np.ndarray]:
    lin = factor.linearize(values)
    A, _ = lin.jacobian()
    sigmas = factor.noiseModel().sigmas() if hasattr(factor.noiseModel(), "sigmas") else None
    out, col = [], 0
    for key in list(factor.keys()):
        d = values.atPose3(key).localCoordinates(values.atPose3(key)).size if gtsam.Symbol(key).chr() == ord("x") else 3
        block = A[:, col:col + d]
        out.append(block * sigmas[:, None] if sigmas is not None else block)
        col += d
    return out


def _values(c=(1.02, 0.01, 1.03)):
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(make_T(rpy_to_R(0.02, -0.03, 0.4), [1.0, 2.0, 0.05])))
    v.insert(X(1), gtsam.Pose3(make_T(rpy_to_R(-0.01, 0.02, 0.7), [1.5, 2.4, 0.02])))
    v.insert(C(1), np.array(c))
    v.insert(L(7), np.array([3.0, 2.5, 0.03]))
    return v


def test_calibrated_wheel_factor_residual_and_jacobians():
    cfg = BackendConfig(odometry={"robust": "none"})
    v = _values()
    D = v.atPose3(X(0)).between(v.atPose3(X(1))).matrix()
    yaw = np.arctan2(D[1, 0], D[0, 0])
    dist = float(np.hypot(D[0, 3], D[1, 3]))
    # Wheels that over-report distance by 2 %, add 0.01 rad of yaw per metre and report 3 % too much turning
    # (a track width configured 3 % too narrow): zero residual at c = (1.02, 0.01, 1.03).
    meas = make_T(rpy_to_R(0, 0, 1.03 * yaw + 0.01 * dist), [1.02 * D[0, 3], 1.02 * D[1, 3], 0.0])
    f = next(g for g in fac.odometry_factors(cfg, 1, meas, dist, calib_key=fac.C(1)) if isinstance(g, gtsam.CustomFactor))
    assert np.abs(f.unwhitenedError(v)).max() < 1e-9
    v_wrong = _values(c=(1.0, 0.0, 1.0))
    err = f.unwhitenedError(v_wrong)
    assert abs(err[1]) > 0.005 and abs(err[0]) > 0.004  # it measures the calibration
    err_yaw_scale = f.unwhitenedError(_values(c=(1.02, 0.01, 1.0)))
    assert abs(err_yaw_scale[0]) == pytest.approx(0.03 * abs(yaw), rel=1e-6) and abs(err_yaw_scale[1:]).max() < 1e-9
    for Ha, Hn in zip(_analytic_jacobians(f, v_wrong), _numerical_jacobians(f, v_wrong)):
        assert np.allclose(Ha, Hn, atol=1e-5), (Ha, Hn)


def test_ground_factor_measures_height_off_the_floor_and_the_base_attitude():
    """The native bearing factor's whitened residual is a point's height off the floor in sigmas (to first
    order), for the pose it was made at and for a tilted one: the floor points hold the base's attitude."""
    cfg = BackendConfig(ground={"robust": "none"})
    sigma = 0.0135
    T = make_T(rpy_to_R(0.0, 0.0, 0.7), [1.0, 2.0, 0.0])
    v = gtsam.Values()
    v.insert(X(1), gtsam.Pose3(T))
    for floor_z in (0.0, -0.05):  # floor at the base origin, or 5 cm below it (camera height override)
        p_base = np.array([2.0, 0.6, floor_z])
        f = fac.ground_factor(X(1), L(7), p_base, floor_z, sigma, cfg)
        for dz in (0.0, 0.004, -0.01):
            vv = gtsam.Values(v)
            vv.insert(L(7), gtsam.Point3(T[:3, :3] @ (p_base + [0, 0, dz]) + T[:3, 3]))
            assert np.sqrt(2 * f.error(vv)) == pytest.approx(abs(dz) / sigma, rel=0.02, abs=1e-6)
    # The same point seen from a base pitched by 0.3 deg: the point sits r * 0.3 deg off its floor.
    p_base = np.array([2.0, 0.6, 0.0])
    f = fac.ground_factor(X(1), L(7), p_base, 0.0, sigma, cfg)
    pitch = np.radians(0.3)
    vv = gtsam.Values()
    vv.insert(X(1), gtsam.Pose3(T @ make_T(rpy_to_R(0.0, pitch, 0.0), [0, 0, 0])))
    vv.insert(L(7), gtsam.Point3(T[:3, :3] @ p_base + T[:3, 3]))
    assert np.sqrt(2 * f.error(vv)) == pytest.approx(2.0 * pitch / sigma, rel=0.05)
    # The azimuth is left to the projection factors: a point moved sideways costs (almost) nothing.
    vv = gtsam.Values(v)
    vv.insert(L(7), gtsam.Point3(T[:3, :3] @ (p_base + [0, 0.05, 0]) + T[:3, 3]))
    assert np.sqrt(2 * f.error(vv)) < 0.05
    with pytest.raises(ValueError):
        fac.ground_factor(X(1), L(7), np.zeros(3), 0.0, sigma, cfg)


def test_level_ground_factor_measures_height_along_the_floor_normal_not_the_base_attitude():
    """The level factor's residual is the point's height above the base origin along the given normal,
    less the floor's z; tilting the base leaves it unchanged (that is its point: a rocking chassis must
    not move its floor points); the Jacobians match numerical ones."""
    cfg = BackendConfig(ground={"robust": "none"})
    up = np.array([0.02, -0.01, 1.0])
    up /= np.linalg.norm(up)
    v = _values()
    f = fac.level_ground_factor(X(1), L(7), up, -0.05, 0.0135, cfg)
    p, t = v.atPoint3(L(7)), v.atPose3(X(1)).translation()
    assert f.unwhitenedError(v)[0] == pytest.approx(up @ (p - t) + 0.05, abs=1e-12)
    tilted = gtsam.Values(v)
    tilted.update(X(1), gtsam.Pose3(v.atPose3(X(1)).matrix() @ make_T(rpy_to_R(0.03, -0.02, 0.0), [0, 0, 0])))
    assert f.unwhitenedError(tilted)[0] == pytest.approx(f.unwhitenedError(v)[0], abs=1e-12)
    raised = gtsam.Values(v)
    raised.update(L(7), p + 0.01 * up)  # 1 cm up along the normal: 1 cm more residual
    assert f.unwhitenedError(raised)[0] - f.unwhitenedError(v)[0] == pytest.approx(0.01, abs=1e-12)
    for Ha, Hn in zip(_analytic_jacobians(f, v), _numerical_jacobians(f, v)):
        assert np.allclose(Ha, Hn, atol=1e-6), (Ha, Hn)


def test_ground_factor_along_a_learnt_floor_normal():
    """With the base z axis as the normal the factor is the plain one; with a tilted normal a point on the
    plane n . q = offset costs nothing and one raised along n by dz costs dz / sigma."""
    cfg = BackendConfig(ground={"robust": "none"})
    sigma = 0.0135
    T = make_T(rpy_to_R(0.0, 0.0, 0.7), [1.0, 2.0, 0.0])
    p_base = np.array([2.0, 0.6, 0.0])
    v = gtsam.Values()
    v.insert(X(1), gtsam.Pose3(T))
    v.insert(L(7), gtsam.Point3(T[:3, :3] @ (p_base + [0, 0, 0.004]) + T[:3, 3]))
    plain = fac.ground_factor(X(1), L(7), p_base, 0.0, sigma, cfg)
    along_z = fac.ground_factor(X(1), L(7), p_base, 0.0, sigma, cfg, np.array([0.0, 0.0, 1.0]))
    assert along_z.error(v) == plain.error(v)
    n = rpy_to_R(0.0, np.radians(-1.0), 0.0)[:, 2]  # a floor tilted by 1 deg in the base frame
    offset = -0.01
    q = np.array([2.0, 0.6, 0.0])
    q = q - (n @ q - offset) * n  # on the plane
    f = fac.ground_factor(X(1), L(7), q, offset, sigma, cfg, n)
    for dz in (0.0, 0.005, -0.01):
        vv = gtsam.Values()
        vv.insert(X(1), gtsam.Pose3(T))
        vv.insert(L(7), gtsam.Point3(T[:3, :3] @ (q + dz * n) + T[:3, 3]))
        assert np.sqrt(2 * f.error(vv)) == pytest.approx(abs(dz) / sigma, rel=0.02, abs=1e-6)


def test_planar_prior_levels_a_tilted_pose_and_keeps_yaw():
    graph = gtsam.NonlinearFactorGraph()
    T_tilted = make_T(rpy_to_R(0.15, -0.1, 0.7), [1.0, 2.0, 0.0])
    graph.add(fac.planar_attitude_factor(X(1), BackendConfig()))
    # a prior that holds position and yaw only (roll and pitch free)
    sig = np.array([10.0, 10.0, 1e-3, 1e-3, 1e-3, 1e-3])
    graph.add(gtsam.PriorFactorPose3(X(1), gtsam.Pose3(T_tilted), gtsam.noiseModel.Diagonal.Sigmas(sig)))
    v = gtsam.Values()
    v.insert(X(1), gtsam.Pose3(T_tilted))
    res = gtsam.LevenbergMarquardtOptimizer(graph, v).optimize().atPose3(X(1)).matrix()
    roll, pitch, yaw = R_to_rpy(res[:3, :3])
    assert abs(roll) < 0.01 and abs(pitch) < 0.01, (roll, pitch)
    assert abs(yaw - 0.7) < 0.02
    assert np.allclose(res[:3, 3], [1.0, 2.0, 0.0], atol=1e-2)



@pytest.mark.parametrize("lm_threshold", [None, 0.3])
def test_relinearisation_thresholds_cover_every_state_kind(lm_threshold):
    """iSAM2 needs a threshold of the right size for every symbol in the graph (else it raises at the
    first relinearisation check): poses, landmarks, floor landmarks and calibration states, all moved far
    enough to be relinearised."""
    cfg = BackendConfig(landmark_relinearize_threshold_m=lm_threshold)
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(fac.relinearize_thresholds(cfg))
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 1.0, 1.0])))
    values.insert(fac.L(1), gtsam.Point3(3.0, 2.0, 2.5))
    values.insert(fac.G(2), gtsam.Point3(2.0, -1.0, 0.5))
    values.insert(fac.C(0), np.array([2.0, 1.0, 1.5]))
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    graph.add(gtsam.PriorFactorPoint3(fac.L(1), gtsam.Point3(1.0, 0.0, 0.5), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    graph.add(gtsam.PriorFactorPoint3(fac.G(2), gtsam.Point3(1.5, 0.0, 0.0), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    graph.add(fac.calibration_prior(0, np.array([1.0, 0.0, 1.0]), np.array([0.03, 0.02, 0.05])))
    isam.update(graph, values)
    for _ in range(3):
        isam.update()  # relinearisation checks over every variable
    est = isam.calculateEstimate()
    assert np.allclose(est.atPoint3(fac.L(1)), [1.0, 0.0, 0.5], atol=1e-6)
    assert np.allclose(est.atPoint3(fac.G(2)), [1.5, 0.0, 0.0], atol=1e-6)
    assert np.allclose(est.atPoint3(fac.C(0)), [1.0, 0.0, 1.0], atol=1e-6)


def test_a_pose_agrees_with_the_wheel_step_within_the_wheel_factors_own_threshold():
    """The initial guess takes PnP's tilt only from a pose the wheel factor would call an inlier."""
    cfg = BackendConfig()
    T_wheels = make_T(rpy_to_R(0.01, -0.01, 0.7), [1.0, 2.0, 0.0])
    near = T_wheels @ make_T(rpy_to_R(0.02, -0.015, 0.001), [0.002, -0.001, 0.004])  # 1.4 deg of rocking, 2 mm
    assert fac.agrees_with_wheel_step(cfg, T_wheels, near, 0.3, 0.0)
    rolled = T_wheels @ make_T(rpy_to_R(0.28, 0.0, 0.0), [0.0, 0.0, 0.0])  # 16 deg: a wrong PnP
    assert not fac.agrees_with_wheel_step(cfg, T_wheels, rolled, 0.3, 0.0)
    shifted = T_wheels @ make_T(np.eye(3), [0.1, 0.0, 0.0])  # 10 cm off a 0.3 m step
    assert not fac.agrees_with_wheel_step(cfg, T_wheels, shifted, 0.3, 0.0)
    turned = T_wheels @ make_T(rpy_to_R(0.0, 0.0, 0.1), [0.0, 0.0, 0.0])  # 5.7 deg of heading
    assert not fac.agrees_with_wheel_step(cfg, T_wheels, turned, 0.3, 0.0)


def test_climb_change_factor_ties_two_steps_climb_rate_not_the_rate_itself():
    cfg = BackendConfig(odometry={"climb_sigma_per_m": 0.01})
    # A base whose mount is pitched 1 deg against T_base_cam: every step climbs 1.7% in the set-up's base frame.
    # The base drives on a level floor along its heading; its attitude (the set-up's base frame) is pitched 1 deg.
    R = rpy_to_R(0.0, np.radians(-1.0), 0.3)
    heading = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    poses = [make_T(R, [0.0, 0.0, 0.0]), make_T(R, 0.4 * heading), make_T(R, 1.0 * heading)]
    v = gtsam.Values()
    for i, T in enumerate(poses):
        v.insert(X(i), gtsam.Pose3(T))
    climbs = [np.linalg.solve(poses[i], poses[i + 1])[2, 3] / d for i, d in enumerate((0.4, 0.6))]
    assert np.abs(climbs) == pytest.approx([np.sin(np.radians(1.0))] * 2, rel=1e-9)  # 1.7% a step in the base frame
    f = fac.climb_change_factor(cfg, 2, 0.4, 0.6)
    assert list(f.keys()) == [X(0), X(1), X(2)]
    assert abs(f.unwhitenedError(v)[0]) < 1e-12  # the same climb rate: no residual however large the rate
    # The second step climbs 1 cm more than the first's rate says: 1 cm x (mean distance / its distance).
    v.update(X(2), gtsam.Pose3(poses[2] @ make_T(np.eye(3), [0.0, 0.0, 0.01])))
    assert f.unwhitenedError(v)[0] == pytest.approx(0.01 * 0.5 / 0.6, rel=1e-6)
    assert f.noiseModel().sigmas()[0] == pytest.approx(0.005)  # 1% of 0.5 m is the 5 mm floor
    assert fac.climb_change_factor(cfg, 2, 0.1, 0.2).noiseModel().sigmas()[0] == pytest.approx(0.005)  # under it
    assert fac.climb_change_factor(cfg, 2, 2.0, 3.0).noiseModel().sigmas()[0] == pytest.approx(0.025)
    # Jacobians against numerical derivatives, at a generic point
    v2 = gtsam.Values()
    for i, T in enumerate([make_T(rpy_to_R(0.02, -0.03, 0.4), [1.0, 2.0, 0.05]),
                           make_T(rpy_to_R(-0.01, 0.02, 0.7), [1.5, 2.4, 0.02]),
                           make_T(rpy_to_R(0.03, 0.01, 0.9), [1.9, 3.0, 0.04])]):
        v2.insert(X(i), gtsam.Pose3(T))
    A, _ = f.linearize(v2).jacobian()
    eps, num = 1e-6, []
    for key in list(f.keys()):
        for j in range(6):
            d = np.zeros(6)
            d[j] = eps
            vp, vm = gtsam.Values(v2), gtsam.Values(v2)
            vp.update(key, v2.atPose3(key).retract(d))
            vm.update(key, v2.atPose3(key).retract(-d))
            num.append((f.unwhitenedError(vp)[0] - f.unwhitenedError(vm)[0]) / (2 * eps))
    assert np.allclose(A[0] * 0.005, num, atol=1e-6)


def test_wheel_climb_ties_only_consecutive_driven_steps_inside_the_window():
    from windowvo.backend.wheel_climb import WheelClimb

    cfg = BackendConfig(odometry={"climb_sigma_per_m": 0.01})
    climb, graph = WheelClimb(cfg), gtsam.NonlinearFactorGraph()
    climb.add(graph, 5, 0.3, False, 0)  # no step before it
    climb.add(graph, 6, 0.3, False, 0)
    assert graph.size() == 1 and list(graph.at(0).keys()) == [X(4), X(5), X(6)]
    climb.add(graph, 8, 0.3, False, 0)  # step 7 was not tied (no wheels there)
    climb.add(graph, 9, 0.01, False, 0)  # standing still: no climb rate
    climb.add(graph, 10, 0.3, False, 8)  # keyframe 8 is the window's oldest
    climb.add(graph, 11, 0.3, True, 0)  # a restarted window
    assert graph.size() == 1
    climb.last = None  # what a window's reset does (SlidingWindowBackend.restart_window)
    climb.add(graph, 12, 0.3, False, 0)
    assert graph.size() == 1
    climb.add(graph, 13, 0.3, False, 0)
    assert graph.size() == 2
    off, graph_off = WheelClimb(BackendConfig()), gtsam.NonlinearFactorGraph()
    off.add(graph_off, 5, 0.3, False, 0)
    off.add(graph_off, 6, 0.3, False, 0)
    assert graph_off.size() == 0  # off by default


def test_a_slipping_wheel_step_loses_its_climb_tie_and_the_next_step_is_not_tied_to_it():
    from windowvo.backend.wheel_climb import WheelClimb

    climb, graph = WheelClimb(BackendConfig(odometry={"climb_sigma_per_m": 0.01})), gtsam.NonlinearFactorGraph()
    climb.add(graph, 4, 0.3, False, 0)
    assert climb.switched([40]) == []  # step 4 slipped but had no climb factor: nothing to remove
    climb.add(graph, 5, 0.3, False, 0)  # nor is step 5 tied to it
    assert graph.size() == 0
    climb.add(graph, 6, 0.3, False, 0)
    graph.add(gtsam.PriorFactorPose3(X(7), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1.0)))
    climb.add(graph, 7, 0.3, False, 0)  # slots: 0 step 6's climb factor, 1 a planar factor's stand-in, 2 step 7's
    assert graph.size() == 3
    assert climb.switched([70, 71, 72]) == [72]  # step 7 slipped: the smoother's index of its climb factor
    climb.add(graph, 8, 0.3, False, 0)  # step 8 is not tied to the slipping step
    assert graph.size() == 3 and climb.slot is None
    climb.add(graph, 9, 0.3, False, 0)
    assert graph.size() == 4 and list(graph.at(3).keys()) == [X(7), X(8), X(9)]
