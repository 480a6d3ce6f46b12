"""The landmark budget against gross outliers: the back end alone over simulated features, rocking loops.

The fixture of ``tests/test_rocking_guess.py`` (loops rocking by 1 deg, exact wheels, exact floor, seeds 8-14),
each back-end setting run over the seven seeds; it prints the median and worst ATE SE(3) and the median wheel-scale
error. ``--outliers`` sets the share of observations the simulation replaces by random pixels (0.05 by default,
as in the tests); with 0 the estimator's error model is exact. Findings: docs/scale_suite.md, "Why more landmarks
can cost the fused runs".

    python scripts/landmark_budget_study.py [--outliers 0.05] [NAME ...]
"""

from __future__ import annotations

import argparse

import numpy as np

from windowvo.backend.smoother import SlidingWindowBackend
from windowvo.config import BackendConfig
from windowvo.eval.metrics import evaluate
from windowvo.io.trajectory import Trajectory
from windowvo.synth.features import FeatureSequence, simulate_features
from windowvo.synth.generate import SynthSpec, WheelErrorModel
from windowvo.synth.paths import PathKind

SEEDS = range(8, 15)
SETTINGS: dict[str, dict] = {
    "default": {},
    "max_landmarks_100": {"max_landmarks": 100},
    "max_landmarks_300": {"max_landmarks": 300},
    "budget_keyframes_1": {"budget_keyframes": 1},
    "extra_iterations_2": {"extra_iterations": 2},
    "budget_keyframes_1_extra_2": {"budget_keyframes": 1, "extra_iterations": 2},
    "cauchy": {"robust": "cauchy"},
    "max_landmarks_300_cauchy": {"max_landmarks": 300, "robust": "cauchy"},
    "budget_keyframes_1_cauchy": {"budget_keyframes": 1, "robust": "cauchy"},
}


def run(fs: FeatureSequence, cfg: BackendConfig) -> tuple[float, float]:
    """ATE SE(3) of the keyframes and |wheel scale - 1| of one back-end run (wheels from the simulation)."""
    be = SlidingWindowBackend(fs.world.camera, cfg, use_odometry=True)
    for i, fo in enumerate(fs.keyframes):
        odom = fs.odometry_step(i)
        be.add_keyframe(fo, odom)
    ts = np.array([f.timestamp for f in fs.keyframes])
    est = Trajectory(ts, np.stack([be.kf_pose[k] for k in range(len(ts))]))
    rep = evaluate(Trajectory(ts, np.stack(fs.gt_T_world_base)), est)
    return rep.ate_se3_rmse_m, abs(be.calibration_with_sigma().scale - 1.0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("names", nargs="*", choices=[[], *SETTINGS], help="settings to run (default: all)")
    p.add_argument("--outliers", type=float, default=0.05, help="share of observations replaced by random pixels")
    a = p.parse_args()
    seqs = [simulate_features(SynthSpec(path=PathKind.LOOP, duration_s=30.0, speed=0.8, seed=s, vibration_deg=1.0,
                                        wheel=WheelErrorModel(scale_error=0.0, yaw_bias_per_m=0.0)),
                              outlier_ratio=a.outliers) for s in SEEDS]
    print(f"| setting (outliers {a.outliers:g}) | ATE median m | ATE worst m | wheel scale error median |\n|---|---|---|---|")
    for name in a.names or list(SETTINGS):
        results = [run(fs, BackendConfig(**SETTINGS[name])) for fs in seqs]
        ates, errors = [r[0] for r in results], [r[1] for r in results]
        print(f"| {name} | {np.median(ates):.4f} | {max(ates):.4f} | {np.median(errors):.4f} |", flush=True)


if __name__ == "__main__":
    main()
