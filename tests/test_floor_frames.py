"""``backend.ground.floor_state``: each keyframe that ties floor points gets a floor frame F(k) of its own,
tied to its base pose with a tilt and a height sigma; its floor points are tied to F(k). Off by default
(measured worse on the scale suite: docs/scale_suite.md, "Floor frames")."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import run_backend

from windowvo.backend.factors import F, X, floor_frame_factor
from windowvo.config import BackendConfig
from windowvo.synth.features import simulate_features
from windowvo.synth.generate import SynthSpec, WheelErrorModel
from windowvo.synth.paths import PathKind


@pytest.fixture(scope="module")
def loop_features():
    spec = SynthSpec(path=PathKind.LOOP, duration_s=30.0, speed=0.8, seed=5,
                     wheel=WheelErrorModel(scale_error=0.02, yaw_bias_per_m=0.005))
    return simulate_features(spec)


def _cfg(**ground) -> BackendConfig:
    return BackendConfig.model_validate({"ground": ground})


def test_the_floor_frame_factor_holds_yaw_and_position_and_frees_tilt_and_height():
    f = floor_frame_factor(3, np.radians(1.0), 0.02)
    assert set(f.keys()) == {X(3), F(3)}
    sig = f.noiseModel().sigmas()
    assert np.allclose(sig[[0, 1]], np.radians(1.0)) and np.isclose(sig[5], 0.02)
    assert np.all(sig[[2, 3, 4]] < 0.01)


def test_floor_frames_carry_the_floor_points(loop_features):
    be, rep = run_backend(loop_features, _cfg(floor_state=True))
    est = be.smoother.calculateEstimate()
    frames = [k for k in range(be.window_start(), be.k + 1) if est.exists(F(k))]
    assert frames, "no keyframe of the window holds a floor frame"
    assert set(frames) <= be.floor.floor_frames
    for k in frames:  # each floor frame sits on its keyframe, within its tilt and height sigmas
        d = np.linalg.inv(est.atPose3(X(k)).matrix()) @ est.atPose3(F(k)).matrix()
        assert abs(d[2, 3]) < 5 * 0.015 * be.floor.camera_height_m and np.degrees(np.arccos(d[2, 2])) < 5.0
    assert be.floor.n_ground_factors > 0
    assert rep.ate_se3_rmse_m < 0.02 * rep.path_length_m


def test_tight_floor_frames_are_the_base_frames(loop_features):
    """The option is what it says: with its sigmas near zero, F(k) is X(k) and the run is the default's."""
    _, rep_off = run_backend(loop_features, _cfg())
    _, rep_tight = run_backend(loop_features, _cfg(floor_state=True, floor_tilt_sigma_deg=1e-3,
                                                   floor_height_fraction=1e-5))
    assert rep_tight.ate_se3_rmse_m == pytest.approx(rep_off.ate_se3_rmse_m, rel=0.05, abs=2e-4)
