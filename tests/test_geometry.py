"""Pose helpers of ``windowvo/geometry.py`` that the back end builds its guesses from."""

import numpy as np

from windowvo.geometry import R_to_rpy, make_T, rpy_to_R, with_tilt_of


def test_with_tilt_of_keeps_position_and_heading_and_takes_roll_and_pitch():
    T_planar = make_T(rpy_to_R(0.0, 0.0, 0.7), [1.0, 2.0, 0.05])
    T_tilt = make_T(rpy_to_R(0.02, -0.03, 2.9), [5.0, -1.0, 0.3])
    T = with_tilt_of(T_planar, T_tilt)
    assert np.allclose(T[:3, 3], T_planar[:3, 3])
    assert np.allclose(R_to_rpy(T[:3, :3]), (0.02, -0.03, 0.7))
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
    assert np.allclose(with_tilt_of(T_planar, T_planar), T_planar)  # a level pose with its own tilt: unchanged


def test_planar_pose_is_a_turn_about_z_at_height_zero():
    from windowvo.geometry import planar_T, rot_z

    for yaw in np.linspace(-7.0, 7.0, 57):
        assert np.array_equal(planar_T(0.3, -2.0, float(yaw)), make_T(rot_z(float(yaw)), [0.3, -2.0, 0.0]))
