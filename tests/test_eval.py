"""Evaluation against known answers: trajectories perturbed by a known offset, scale and drift.

Every expected number below is derived by hand from the fixture's geometry (see each test's
docstring), never by running the metric on another input.

Fixtures:

* ``circle``: N poses on a circle of radius r about the origin (z = 0), theta_i = 2 pi i / N,
  heading along the tangent (turning left, so the base's +y points at the centre). Consecutive
  poses are one chord ``l = 2 r sin(pi / N)`` apart; the path length is ``(N - 1) l``; the
  positions' mean is the centre and their mean squared distance to it is ``r^2``. RPE uses
  consecutive pairs 1 m apart along the ground truth, so with ``k = ceil(1 / l)`` every pair is
  ``(i, i + k)`` and turns the heading by ``phi_k = 2 pi k / N``.
* ``out_and_back``: a half circle out and the same half circle back (N odd, N = 2 m + 1), so
  ``p_i = p_(N-1-i)`` and every step is one chord ``2 r sin(pi / (2 m))`` long.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from windowvo.errors import WindowVOError
from windowvo.eval.metrics import evaluate
from windowvo.geometry import make_T, rot_z, rpy_to_R
from windowvo.io.trajectory import Trajectory, write_tum

R_CIRCLE = 5.0
N_CIRCLE = 200
CHORD = 2.0 * R_CIRCLE * math.sin(math.pi / N_CIRCLE)  # 0.157 m
K = math.ceil(1.0 / CHORD)  # 7 steps per RPE pair
PATH_CIRCLE = (N_CIRCLE - 1) * CHORD

# A rigid transform of the whole estimate (its world is not the ground truth's world).
W = make_T(rpy_to_R(0.3, -0.2, 1.1), [10.0, -4.0, 2.5])


def circle() -> Trajectory:
    theta = 2.0 * np.pi * np.arange(N_CIRCLE) / N_CIRCLE
    poses = np.stack([make_T(rot_z(th + np.pi / 2), [R_CIRCLE * np.cos(th), R_CIRCLE * np.sin(th), 0.0])
                      for th in theta])
    return Trajectory(0.1 * np.arange(N_CIRCLE), poses)


def with_positions(traj: Trajectory, positions: np.ndarray) -> Trajectory:
    poses = traj.T_world_base.copy()
    poses[:, :3, 3] = positions
    return Trajectory(traj.timestamps.copy(), poses)


def transformed(traj: Trajectory, T_left: np.ndarray, T_right: np.ndarray | None = None) -> Trajectory:
    T_right = np.eye(4) if T_right is None else T_right
    return Trajectory(traj.timestamps.copy(), np.einsum("ij,njk,kl->nil", T_left, traj.T_world_base, T_right))


def test_fixture_step_count():
    # the RPE pairs are 7 chords apart, with a margin on both sides of 1 m
    assert K == 7 and (K - 1) * CHORD < 0.95 and K * CHORD > 1.05


def test_rigid_offset_of_the_whole_estimate_costs_nothing():
    """An estimate in another world frame (rotated and shifted): every metric is zero, scale 1."""
    gt = circle()
    rep = evaluate(gt, transformed(gt, W))
    assert rep.n_poses == N_CIRCLE
    assert rep.path_length_m == pytest.approx(PATH_CIRCLE, rel=1e-12)
    assert rep.ate_se3_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert rep.ate_sim3_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert rep.sim3_scale == pytest.approx(1.0, abs=1e-12)
    assert rep.rpe_trans_per_m == pytest.approx(0.0, abs=1e-9)
    assert rep.end_drift_pct == pytest.approx(0.0, abs=1e-9)


def test_body_frame_offset():
    """The estimate tracks a point ``a`` to the left of the base (a lever-arm error), in another world.

    Its positions lie on the circle of radius ``r - a`` about the same centre, so:
    ATE SE(3) = a (rotation identity, no translation); Sim(3) scale r / (r - a) and ATE 0;
    each RPE pair's error is ``|o - R(phi_k)^T o| = 2 a sin(phi_k / 2)``; after aligning the first
    pose the end point is off by ``|R(phi_end) o - o| = 2 a sin(pi / N)``, phi_end = 2 pi (N-1) / N.
    """
    a = 0.3
    gt = circle()
    est = transformed(gt, W, make_T(np.eye(3), [0.0, a, 0.0]))
    rep = evaluate(gt, est)
    assert rep.ate_se3_rmse_m == pytest.approx(a, rel=1e-9)
    assert rep.sim3_scale == pytest.approx(R_CIRCLE / (R_CIRCLE - a), rel=1e-9)
    assert rep.ate_sim3_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert rep.rpe_trans_per_m == pytest.approx(2.0 * a * math.sin(math.pi * K / N_CIRCLE), rel=1e-9)
    end_err = 2.0 * a * math.sin(math.pi / N_CIRCLE)
    assert rep.end_drift_pct == pytest.approx(100.0 * end_err / PATH_CIRCLE, rel=1e-9)


@pytest.mark.parametrize("s", [0.8, 1.25])
def test_known_scale(s):
    """Positions scaled by s about the centre, in another world.

    Rigid alignment cannot fix the scale: ATE SE(3) = |1 - s| r. Sim(3) scale 1 / s, ATE 0.
    RPE over 1 m of *ground truth* path: |1 - s| times the chord of k steps, 2 r sin(pi k / N).
    End drift: |1 - s| times the first-to-last chord, 2 r sin(pi / N).
    """
    gt = circle()
    est = transformed(with_positions(gt, s * gt.positions), W)
    rep = evaluate(gt, est)
    assert rep.ate_se3_rmse_m == pytest.approx(abs(1.0 - s) * R_CIRCLE, rel=1e-9)
    assert rep.sim3_scale == pytest.approx(1.0 / s, rel=1e-9)
    assert rep.ate_sim3_rmse_m == pytest.approx(0.0, abs=1e-9)
    chord_k = 2.0 * R_CIRCLE * math.sin(math.pi * K / N_CIRCLE)
    assert rep.rpe_trans_per_m == pytest.approx(abs(1.0 - s) * chord_k, rel=1e-9)
    end_err = abs(1.0 - s) * 2.0 * R_CIRCLE * math.sin(math.pi / N_CIRCLE)
    assert rep.end_drift_pct == pytest.approx(100.0 * end_err / PATH_CIRCLE, rel=1e-9)
    assert not rep.monocular


def test_monocular_rpe_and_drift_are_in_the_sim3_scale():
    """A monocular estimate in an arbitrary unit (s = 0.01) whose shape is exact: after the
    Sim(3) scale its RPE and end drift are 0, and no arbitrary-scale number is reported."""
    gt = circle()
    est = transformed(with_positions(gt, 0.01 * gt.positions), W)
    rep = evaluate(gt, est, monocular=True)
    assert rep.monocular
    assert rep.sim3_scale == pytest.approx(100.0, rel=1e-9)
    assert rep.rpe_trans_per_m == pytest.approx(0.0, abs=1e-9)
    assert rep.end_drift_pct == pytest.approx(0.0, abs=1e-9)
    d = rep.as_dict()
    assert d["ate_se3_rmse_m"] is None and d["monocular"] is True
    assert d["rpe_trans_per_m"] == pytest.approx(0.0, abs=1e-9)
    line = rep.summary()
    assert "ATE SE(3) n/a" in line and "after Sim(3) scale" in line
    assert "RPE 0.000 m per m after Sim(3) scale" in line and "end drift 0.00%" in line
    # the same estimate evaluated as metric: RPE is the (huge) unscaled error, |1 - 0.01| of each chord
    metric = evaluate(gt, est)
    chord_k = 2.0 * R_CIRCLE * math.sin(math.pi * K / N_CIRCLE)
    assert metric.rpe_trans_per_m == pytest.approx(0.99 * chord_k, rel=1e-9)
    # shown as monocular, a report computed as metric omits RPE and drift rather than print them
    assert "RPE and end drift n/a" in metric.summary(metric=False)
    assert f"RPE {metric.rpe_trans_per_m:.3f} m per m" in metric.summary()


def test_monocular_without_a_scale_reports_no_rpe():
    """A straight line has no unique Sim(3) alignment: scale unknown, so no RPE or drift."""
    n = 40
    poses = np.stack([make_T(np.eye(3), [0.1 * i, 0.0, 0.0]) for i in range(n)])
    gt = Trajectory(0.1 * np.arange(n), poses)
    rep = evaluate(gt, with_positions(gt, 0.5 * gt.positions), monocular=True)
    assert math.isnan(rep.sim3_scale) and math.isnan(rep.rpe_trans_per_m) and math.isnan(rep.end_drift_pct)
    d = rep.as_dict()
    assert d["rpe_trans_per_m"] is None and d["end_drift_pct"] is None and d["sim3_scale"] is None
    json.dumps(d, allow_nan=False)  # valid JSON, no NaN
    assert "RPE and end drift n/a (scale unknown)" in rep.summary()


M_HALF = 60
N_BACK = 2 * M_HALF + 1
R_BACK = 4.0
STEP_BACK = 2.0 * R_BACK * math.sin(math.pi / (2 * M_HALF))  # 0.209 m
K_BACK = math.ceil(1.0 / STEP_BACK)  # 5


def out_and_back() -> Trajectory:
    idx = np.arange(N_BACK)
    theta = np.pi * np.minimum(idx, N_BACK - 1 - idx) / M_HALF
    going_back = idx > M_HALF
    poses = []
    for th, back in zip(theta, going_back):
        yaw = th - np.pi / 2 if back else th + np.pi / 2
        poses.append(make_T(rot_z(yaw), [R_BACK * np.cos(th), R_BACK * np.sin(th), 0.0]))
    return Trajectory(0.1 * idx, np.stack(poses))


def test_known_drift():
    """A vertical drift growing linearly to d at the end: c_i = d i / (N - 1).

    On the out-and-back path, c_i - mean(c) is odd and p_i - mean(p) even under i -> N-1-i, so
    the drift is uncorrelated with the positions: the best rotation is the identity and
    ATE SE(3) = std(c) = d sqrt((N + 1) / (12 (N - 1))). Sim(3): scale
    var(p) / (var(p) + var(c)) and ATE^2 = (1 - scale)^2 var(p) + scale^2 var(c). Each RPE pair
    (i, i + k) is off by d k / (N - 1); the end point by d.
    """
    d = 0.5
    gt = out_and_back()
    assert np.allclose(gt.positions, gt.positions[::-1])
    steps = np.linalg.norm(np.diff(gt.positions, axis=0), axis=1)
    assert np.allclose(steps, STEP_BACK) and K_BACK == 5 and (K_BACK - 1) * STEP_BACK < 0.9
    c = d * np.arange(N_BACK) / (N_BACK - 1)
    est = transformed(with_positions(gt, gt.positions + c[:, None] * np.array([0.0, 0.0, 1.0])), W)
    rep = evaluate(gt, est)
    path = (N_BACK - 1) * STEP_BACK
    assert rep.path_length_m == pytest.approx(path, rel=1e-12)
    assert rep.ate_se3_rmse_m == pytest.approx(d * math.sqrt((N_BACK + 1) / (12.0 * (N_BACK - 1))), rel=1e-9)
    var_c = d**2 * (N_BACK + 1) / (12.0 * (N_BACK - 1))
    var_p = float(np.mean(np.sum((gt.positions - gt.positions.mean(axis=0)) ** 2, axis=1)))
    scale = var_p / (var_p + var_c)
    assert rep.sim3_scale == pytest.approx(scale, rel=1e-9)
    assert rep.ate_sim3_rmse_m == pytest.approx(math.sqrt((1 - scale) ** 2 * var_p + scale**2 * var_c), rel=1e-9)
    assert rep.rpe_trans_per_m == pytest.approx(d * K_BACK / (N_BACK - 1), rel=1e-9)
    assert rep.end_drift_pct == pytest.approx(100.0 * d / path, rel=1e-9)


def test_too_few_common_poses_is_an_error():
    gt = circle()
    late = Trajectory(gt.timestamps + 1000.0, gt.T_world_base.copy())
    with pytest.raises(WindowVOError, match="cannot associate"):
        evaluate(gt, late)


def _eval_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "windowvo.eval", *args], capture_output=True, text=True, timeout=300)


def test_eval_command_line_on_a_known_answer(tmp_path):
    """The CLI on files: the body-frame offset of ``test_body_frame_offset`` (a = 0.2 m)."""
    a = 0.2
    gt = circle()
    est = transformed(gt, W, make_T(np.eye(3), [0.0, a, 0.0]))
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)
    write_tum(tmp_path / "est.txt", est.timestamps, est.T_world_base)
    r = _eval_cli(str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    # the TUM file rounds positions to 1e-6 m and quaternions to 1e-9
    assert rep["n_poses"] == N_CIRCLE
    assert rep["ate_se3_rmse_m"] == pytest.approx(a, abs=1e-5)
    assert rep["sim3_scale"] == pytest.approx(R_CIRCLE / (R_CIRCLE - a), abs=1e-5)
    assert rep["rpe_trans_per_m"] == pytest.approx(2.0 * a * math.sin(math.pi * K / N_CIRCLE), abs=1e-5)
    assert rep["end_drift_pct"] == pytest.approx(100.0 * 2.0 * a * math.sin(math.pi / N_CIRCLE) / PATH_CIRCLE,
                                                 abs=1e-4)
    text = _eval_cli(str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"))
    assert text.returncode == 0 and "ATE SE(3) 0.200 m" in text.stdout
    assert f"RPE {2.0 * a * math.sin(math.pi * K / N_CIRCLE):.3f} m per m" in text.stdout


def test_eval_command_line_treats_an_up_to_scale_estimate_as_monocular(tmp_path):
    """windowvo writes 'up to scale' into a monocular trajectory's header; the CLI then reports
    RPE and drift after the Sim(3) scale (here a pure scale of 0.01: both zero)."""
    gt = circle()
    est = transformed(with_positions(gt, 0.01 * gt.positions), W)
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)
    write_tum(tmp_path / "est.txt", est.timestamps, est.T_world_base,
              header="windowvo estimate\nmonocular run: translation is up to scale")
    r = _eval_cli(str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["monocular"] is True and rep["ate_se3_rmse_m"] is None
    assert rep["sim3_scale"] == pytest.approx(100.0, rel=1e-4)
    assert rep["rpe_trans_per_m"] == pytest.approx(0.0, abs=1e-4)
    assert rep["end_drift_pct"] == pytest.approx(0.0, abs=1e-3)
    # the same file with --metric is taken at its word: RPE 0.99 of each 1 m chord
    m = json.loads(_eval_cli(str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json", "--metric").stdout)
    assert m["rpe_trans_per_m"] == pytest.approx(0.99 * 2.0 * R_CIRCLE * math.sin(math.pi * K / N_CIRCLE), abs=1e-5)


def test_eval_command_line_bad_input_is_one_line(tmp_path):
    write_tum(tmp_path / "gt.txt", circle().timestamps, circle().T_world_base)
    (tmp_path / "bad.txt").write_text("0 1 2 3\n")
    r = _eval_cli(str(tmp_path / "gt.txt"), str(tmp_path / "bad.txt"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0 and "expected 8 numbers" in r.stderr
