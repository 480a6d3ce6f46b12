"""``backend.ground.height_sigma_fraction``: the floor's depth below its configured height as a state ``D(k)`` shared
by the keyframes, so that the floor tells the scale no better than the camera height is known. Off by default
(measured worse on the scale suite's rendered floors, which are exact: docs/scale_suite.md, "The floor's depth")."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from conftest import run_backend

from windowvo.backend.factors import D, F, X, floor_depth_factor
from windowvo.config import BackendConfig
from windowvo.synth.features import simulate_features
from windowvo.synth.generate import SynthSpec, WheelErrorModel
from windowvo.synth.paths import PathKind


@pytest.fixture(scope="module")
def exact_wheels():
    spec = SynthSpec(path=PathKind.LOOP, duration_s=30.0, speed=0.8, seed=5,
                     wheel=WheelErrorModel(scale_error=0.0, yaw_bias_per_m=0.0))
    return simulate_features(spec)


def _values(depth: float, rng: np.random.Generator) -> gtsam.Values:
    v = gtsam.Values()
    T = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.3, 3)), rng.normal(0, 2, 3))
    Fp = T.compose(gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.01, 3)), np.array([0.01, -0.02, -depth + 0.03])))
    v.insert(X(2), T)
    v.insert(F(2), Fp)
    v.insert(D(2), float(depth))
    return v


def test_the_depth_factor_is_zero_on_a_pure_drop_and_its_jacobians_are_right():
    f = floor_depth_factor(2, D(2))
    v = gtsam.Values()
    T = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.1, -0.2, 0.7), np.array([1.0, 2.0, 0.3]))
    v.insert(X(2), T)
    v.insert(F(2), T.compose(gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, -0.04]))))
    v.insert(D(2), 0.04)
    assert np.allclose(f.unwhitenedError(v), 0.0, atol=1e-12)
    rng = np.random.default_rng(0)
    v = _values(0.05, rng)
    lin = f.linearize(v)
    A, _ = lin.jacobian()  # whitened: A = J / sigma
    sigma = f.noiseModel().sigmas()[0]
    e0 = f.unwhitenedError(v)
    numeric = []
    eps = 1e-6
    for key, dim in ((X(2), 6), (F(2), 6), (D(2), 1)):
        for i in range(dim):
            w = gtsam.Values(v)
            if dim == 6:
                delta = np.zeros(6)
                delta[i] = eps
                w.update(key, v.atPose3(key).retract(delta))
            else:
                w.update(key, v.atDouble(key) + eps)
            numeric.append((f.unwhitenedError(w) - e0) / eps)
    assert np.allclose(A * sigma, np.array(numeric).T, atol=1e-4)


def _cfg(**ground) -> BackendConfig:
    return BackendConfig.model_validate({"ground": ground})


def test_a_loose_height_lets_exact_wheels_correct_a_wrong_camera_height(exact_wheels):
    """The camera height told 5% too high, the wheels exact: tied to the configured floor the run takes the floor's
    scale (0.184 m, scale 0.96); with the height known to 10% the depth state takes the error and the run follows the
    wheels (0.010 m). The depth should be -0.05 / 1.05 of the configured height, less the share the wheels' 3% prior
    leaves to the floor (0.1^2 / (0.1^2 + 0.03^2): at least 92% of it)."""
    h = float(exact_wheels.world.camera.T_base_cam[2, 3])
    wrong = {"camera_height_m": 1.05 * h}
    _, rep_exact = run_backend(exact_wheels, _cfg(**wrong))
    be, rep_state = run_backend(exact_wheels, _cfg(**wrong, height_sigma_fraction=0.10))
    assert be.floor.depth.live and be.floor.floor_frames
    depth_share = be.floor.depth.depth_m / (1.05 * h)
    assert -0.055 < depth_share < -0.04, depth_share
    assert be.scale_report().floor_depth_m == be.floor.depth.depth_m  # summary.json's floor_depth_m
    assert rep_state.ate_se3_rmse_m < 0.6 * rep_exact.ate_se3_rmse_m


def test_a_tight_height_is_the_configured_floor(exact_wheels):
    """The check above can fail: with the height known to 0.01% the depth stays at zero and the run is the
    default's (within 5%: its floor frames are held to their keyframes by 1 mm and 1 mrad, not exactly)."""
    _, rep_off = run_backend(exact_wheels, _cfg())
    be, rep_tight = run_backend(exact_wheels, _cfg(height_sigma_fraction=1e-4))
    assert abs(be.floor.depth.depth_m) < 1e-3
    assert run_backend(exact_wheels, _cfg())[0].scale_report().floor_depth_m is None  # not estimated: not reported
    assert rep_tight.ate_se3_rmse_m == pytest.approx(rep_off.ate_se3_rmse_m, rel=0.05, abs=2e-4)


def test_floor_frames_and_the_depth_state_are_refused_together(tmp_path):
    """One line at load, not a run that silently takes one of them."""
    from windowvo.config import ConfigError, load_config

    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"sequence: {tmp_path}\noutput: {tmp_path / 'out'}\n")
    with pytest.raises(ConfigError, match="floor_state and height_sigma_fraction"):
        load_config(cfg, ["backend.ground.floor_state=true", "backend.ground.height_sigma_fraction=0.02"])
    load_config(cfg, ["backend.ground.height_sigma_fraction=0.02"])  # either alone loads
