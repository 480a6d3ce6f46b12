"""``backend.landmark_model: smart``: landmarks off the floor as GTSAM smart projection factors (no point state).

The bookkeeping (one factor per landmark, replaced by each new observation, ended when the fixed-lag smoother
marginalises its oldest keyframe) is checked on feature-level data; a rendered loop checks a whole run."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from conftest import make_config

from windowvo.backend.factors import LANDMARK_SYMBOL, X
from windowvo.backend.smoother import SlidingWindowBackend
from windowvo.config import BackendConfig, LandmarkModel
from windowvo.eval.metrics import evaluate
from windowvo.io.trajectory import Trajectory
from windowvo.runtime.job import run_job
from windowvo.synth.features import simulate_features
from windowvo.synth.generate import SynthSpec, WheelErrorModel
from windowvo.synth.paths import PathKind
from windowvo.types import OdometryStep

SMART_FACTOR = gtsam.SmartProjectionPoseFactorCal3_S2
# ATE SE(3) bound on the rendered 12 s loop (9.6 m) that both models must meet (both measured 0.0041 m).
RENDERED_LOOP_ATE_BOUND_M = 0.006


@pytest.fixture(scope="module")
def features():
    spec = SynthSpec(path=PathKind.LOOP, duration_s=25.0, speed=0.8, seed=3,
                     wheel=WheelErrorModel(scale_error=0.01, yaw_bias_per_m=0.01))
    return simulate_features(spec, pixel_noise=0.5, outlier_ratio=0.05)


def _odometry(fs, i: int) -> OdometryStep | None:
    if i == 0:
        return None
    t0, t1 = fs.keyframes[i - 1].timestamp, fs.keyframes[i].timestamp
    return OdometryStep(fs.odometry.delta(t0, t1), fs.odometry.distance(t0, t1))


def _smart_in_graph(be: SlidingWindowBackend) -> dict[int, SMART_FACTOR]:
    """The smoother's smart factors by slot."""
    g = be.smoother.getFactors()
    out = {}
    for i in range(g.size()):
        if g.exists(i) and isinstance(g.at(i), SMART_FACTOR):
            out[i] = g.at(i)
    return out


def _smart_landmarks(be: SlidingWindowBackend) -> dict[int, tuple[int, list[int]]]:
    """Track id -> (its factor's slot, its observations' keyframes), of the live smart landmarks."""
    out = {}
    for tid, lm in be.lm.landmarks.items():
        if lm.smart is not None:
            assert len(lm.factor_indices) == 1, (tid, lm.factor_indices)
            out[tid] = (lm.factor_indices[0][1], [kk for kk, _, _ in lm.smart.observations])
    return out


def test_each_observation_replaces_the_factor_and_marginalised_ones_end(features):
    fs = features
    cfg = BackendConfig(landmark_model=LandmarkModel.SMART)
    be = SlidingWindowBackend(fs.world.camera, cfg, use_odometry=True)
    replaced = ended = 0
    for i, fo in enumerate(fs.keyframes):
        before = _smart_landmarks(be)
        be.add_keyframe(fo, _odometry(fs, i))
        assert be.n_resets == 0
        after, in_graph = _smart_landmarks(be), _smart_in_graph(be)
        # Exactly one factor per live smart landmark, in its slot, over its observations (no stale factor left).
        assert set(in_graph) == {slot for slot, _ in after.values()}
        for slot, kfs in after.values():
            assert list(in_graph[slot].keys()) == [X(kk) for kk in kfs]
            assert kfs[0] >= be.window_start()
        for tid, (_, kfs) in after.items():
            if tid in before and kfs[-1] == be.k:  # seen again: a new factor with one more observation
                assert kfs == before[tid][1] + [be.k]
                replaced += 1
        ended += sum(1 for tid, (_, kfs) in before.items() if tid not in after and kfs[0] < be.window_start())
    assert replaced > 500 and ended > 20, (replaced, ended)
    # No point state for the landmarks off the floor; the floor's stay explicit.
    keys = [gtsam.Symbol(k) for k in be.smoother.timestamps()]
    assert not any(chr(s.chr()) == LANDMARK_SYMBOL for s in keys)
    assert any(lm.smart is None and lm.on_ground for lm in be.lm.landmarks.values())


def _feature_level_ate(fs, model: LandmarkModel | None) -> float:
    """ATE SE(3) of the back end on feature-level data (``model`` None: wheels alone, no vision)."""
    be = SlidingWindowBackend(fs.world.camera, BackendConfig(landmark_model=model or LandmarkModel.EXPLICIT),
                              use_odometry=True)
    for i, fo in enumerate(fs.keyframes):
        fo.vision_ok = model is not None
        be.add_keyframe(fo, _odometry(fs, i))
        fo.vision_ok = True
    assert be.n_resets == 0
    ts = np.array([f.timestamp for f in fs.keyframes])
    est = Trajectory(ts, np.stack([be.kf_pose[k] for k in range(len(ts))]))
    return evaluate(Trajectory(ts, np.stack(fs.gt_T_world_base)), est).ate_se3_rmse_m


def test_feature_level_accuracy_of_both_models(features):
    """Same data, both models: the smart one within 20% of the explicit one, both well below the wheels alone
    (measured: explicit 0.0857 m, smart 0.0869 m, wheels alone 0.182 m, over 19.8 m)."""
    ate = {model: _feature_level_ate(features, model) for model in LandmarkModel}
    wheels = _feature_level_ate(features, None)
    assert ate[LandmarkModel.SMART] <= 1.2 * ate[LandmarkModel.EXPLICIT], ate
    assert max(ate.values()) < 0.6 * wheels, (ate, wheels)


def test_rendered_loop_runs_with_smart_factors(short_loop, tmp_path):
    """A whole run on the rendered 12 s loop: no smoother failure, and within the bound the explicit model also
    meets (measured: ATE SE(3) explicit 0.00411 m, smart 0.00411 m, over 9.6 m)."""
    rep = run_job(make_config(short_loop, tmp_path / "out", backend={"landmark_model": "smart"}))
    assert rep.result.n_resets == 0
    assert rep.accuracy.ate_se3_rmse_m < RENDERED_LOOP_ATE_BOUND_M


@pytest.mark.slow
def test_rendered_loop_explicit_meets_the_same_bound(short_loop, tmp_path):
    rep = run_job(make_config(short_loop, tmp_path / "out", backend={"landmark_model": "explicit"}))
    assert rep.result.n_resets == 0
    assert rep.accuracy.ate_se3_rmse_m < RENDERED_LOOP_ATE_BOUND_M
