"""A solve that runs off is caught, not passed on: the constant-velocity guess keeps its rotation a rotation,
and an estimate whose keyframe pose is no rigid motion counts as a failed update (the window resets).

Found by the scale suite: a monocular run without a metric cue on a rendered street (PnP failing keyframe
after keyframe, so each guess extrapolated the last two poses) multiplied its rotations' rounding error by
1 + sqrt(2) per keyframe until they were matrices of 1e-226 and the smoother could not restart."""

from __future__ import annotations

import gtsam
import numpy as np

from windowvo.backend.factors import X
from windowvo.backend.smoother import diverged_keyframe
from windowvo.geometry import extrapolate_T, inv_T, make_T, nearest_rotation, rpy_to_R


def _orthonormality_error(R: np.ndarray) -> float:
    return float(np.abs(R.T @ R - np.eye(3)).max())


def test_nearest_rotation_is_a_rotation_and_leaves_one_alone():
    R = rpy_to_R(0.1, -0.2, 0.7)
    assert np.allclose(nearest_rotation(R), R, atol=1e-14)
    noisy = R + 1e-3 * np.random.default_rng(0).normal(size=(3, 3))
    Rn = nearest_rotation(noisy)
    assert _orthonormality_error(Rn) < 1e-14 and np.linalg.det(Rn) > 0
    assert np.abs(Rn - R).max() < 5e-3
    assert np.linalg.det(nearest_rotation(-R)) > 0  # a reflection's nearest rotation, not the reflection


def test_extrapolating_pose_after_pose_keeps_rotations():
    step = make_T(rpy_to_R(0.01, 0.02, 0.05), [0.5, 0.02, 0.01])
    T_before = np.eye(4)
    T_before[:3, :3] += 1e-9  # a rounding error, as an estimate carries one
    T_last = T_before @ step
    naive_before, naive_last = T_before.copy(), T_last.copy()
    for _ in range(40):
        T_before, T_last = T_last, extrapolate_T(T_before, T_last)
        with np.errstate(all="ignore"):
            naive_before, naive_last = naive_last, naive_last @ inv_T(naive_before) @ naive_last
    assert _orthonormality_error(T_last[:3, :3]) < 1e-12
    assert np.allclose(T_last[:3, 3], (np.linalg.matrix_power(step, 41))[:3, 3], rtol=1e-3)
    # Without the re-orthonormalisation the same recurrence runs off: the check above can fail.
    assert not np.all(np.isfinite(naive_last)) or _orthonormality_error(naive_last[:3, :3]) > 1.0


def test_a_pose_that_is_no_rigid_motion_is_found():
    values = gtsam.Values()
    values.insert(X(3), gtsam.Pose3(make_T(rpy_to_R(0.0, 0.1, 0.3), [1.0, 2.0, 0.0])))
    assert diverged_keyframe(values, range(0, 5)) is None  # keys the estimate lacks are skipped
    bad = np.eye(4)
    bad[:3, :3] *= 1e-3
    values.insert(X(4), gtsam.Pose3(bad))
    assert diverged_keyframe(values, range(0, 5)) == 4
