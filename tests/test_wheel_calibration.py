"""The wheel calibration states C(k) on their own (``windowvo/backend/wheel_calibration.py``): when they start,
one state per block of keyframes that leave the window together, the random walk over the distance driven,
and a window reset's restart of the chain."""

import gtsam
import numpy as np

from windowvo.backend.factors import C
from windowvo.backend.wheel_calibration import RESET_CALIBRATION_SIGMA_FACTOR, WheelCalibrationStates
from windowvo.config import BackendConfig


def _step(states: WheelCalibrationStates, k: int, distance_m: float | None = 0.5):
    graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
    key = states.step_key(graph, values, stamps, k, distance_m)
    return key, graph, values, stamps


def test_states_start_with_the_floor_one_per_block_with_a_random_walk_over_the_distance():
    cfg = BackendConfig(window_keyframes=8, marginalize_every=4)
    wc = cfg.wheel_calibration
    states = WheelCalibrationStates(cfg, use_odometry=True)
    assert WheelCalibrationStates(cfg, use_odometry=False).wanted is False
    states.start_with_floor(2, n_ground_keyframes=0)
    assert not states.calibrate and _step(states, 2)[0] is None  # no floor yet: no state
    states.start_with_floor(3, n_ground_keyframes=1)
    assert states.calibrate and states.start == 3
    key, graph, values, stamps = _step(states, 3)
    assert key == C(3) and graph.size() == 1 and values.exists(C(3)) and stamps == {C(3): 3.0}
    assert np.allclose(graph.at(0).noiseModel().sigmas(),
                       [wc.scale_prior_sigma, wc.yaw_bias_prior_sigma, wc.yaw_scale_prior_sigma])
    # keyframe 4 is in the same block ((4 + 7) % 4 != 0): the state's stamp is refreshed, nothing is added
    key, graph, values, stamps = _step(states, 4, 0.7)
    assert key == C(3) and graph.size() == 0 and values.size() == 0 and stamps == {C(3): 4.0}
    # keyframe 5 starts a block: a new state with a random walk over the distance driven since C(3)
    assert states.block_starts(5) and not states.block_starts(6)
    key, graph, values, stamps = _step(states, 5)
    assert key == C(5) and graph.size() == 1 and list(graph.at(0).keys()) == [C(3), C(5)]
    d = np.sqrt(0.5 + 0.7)  # the steps of keyframes 3 and 4, which went through C(3)
    assert np.allclose(graph.at(0).noiseModel().sigmas(),
                       [wc.scale_walk_per_sqrt_m * d, wc.yaw_bias_walk_per_sqrt_m * d, wc.yaw_scale_walk_per_sqrt_m * d])
    key, graph, _, _ = _step(states, 6)
    assert key == C(5) and graph.size() == 0  # within the block: no new state


def test_a_reset_restarts_the_chain_from_the_last_estimate():
    cfg = BackendConfig(window_keyframes=8, marginalize_every=4)
    wc = cfg.wheel_calibration
    states = WheelCalibrationStates(cfg, use_odometry=True)
    states.start_with_floor(9, n_ground_keyframes=1)
    states.forget_failed_start(9)  # the update that started it failed: not started
    assert not states.calibrate and states.key == -1
    states.start_with_floor(10, n_ground_keyframes=1)
    _step(states, 10)
    est = gtsam.Values()
    est.insert(C(10), np.array([1.03, 0.01, 0.98]))
    states.read(est)
    assert (states.calib.scale, states.calib.yaw_bias_per_m, states.calib.yaw_scale) == (1.03, 0.01, 0.98)
    states.forget_failed_start(12)  # started before the failed update: kept
    assert states.calibrate
    graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
    states.restart_from_previous(graph, values, stamps, 12)
    f = RESET_CALIBRATION_SIGMA_FACTOR
    assert states.key == 11 and stamps == {C(11): 11.0} and np.allclose(values.atPoint3(C(11)), [1.03, 0.01, 0.98])
    assert np.allclose(graph.at(0).noiseModel().sigmas(),
                       [f * wc.scale_prior_sigma, f * wc.yaw_bias_prior_sigma, f * wc.yaw_scale_prior_sigma])
    graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
    states.restart_here(graph, values, stamps, 13)  # from this keyframe alone: the full prior
    assert states.start == 13 and states.key == 13 and graph.size() == 1
    assert np.allclose(graph.at(0).noiseModel().sigmas(),
                       [wc.scale_prior_sigma, wc.yaw_bias_prior_sigma, wc.yaw_scale_prior_sigma])


def test_the_calibration_starts_from_the_configured_initial_values():
    from windowvo.backend.wheel_calibration import WheelCalibrationStates
    from windowvo.config import BackendConfig

    cfg = BackendConfig.model_validate({"wheel_calibration": {"initial_scale": 1.021, "initial_yaw_bias_per_m": 0.004,
                                                              "initial_yaw_scale": 1.03}})
    states = WheelCalibrationStates(cfg, use_odometry=True)
    assert (states.calib.scale, states.calib.yaw_bias_per_m, states.calib.yaw_scale) == (1.021, 0.004, 1.03)
    default = WheelCalibrationStates(BackendConfig(), use_odometry=True)
    assert (default.calib.scale, default.calib.yaw_bias_per_m, default.calib.yaw_scale) == (1.0, 0.0, 1.0)
