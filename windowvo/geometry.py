"""Pure SE(3) helpers on 4x4 numpy matrices.

Naming rule (used across windowvo): ``T_a_b`` maps points expressed in frame ``b`` into
frame ``a``, so ``p_a = T_a_b @ p_b`` and ``T_a_c = T_a_b @ T_b_c``. Frames: ``world``
(the base at the first frame), ``base`` (robot: x forward, y left, z up), ``cam``
(x right, y down, z forward), ``odom`` (the wheel-odometry frame).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

# Rotation that maps camera-axis vectors (x right, y down, z forward) into base axes
# (x forward, y left, z up) for a camera looking straight ahead.
R_BASE_CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def make_T(R: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation closest to a 3x3 matrix (Frobenius norm; SVD, with the determinant's sign fixed)."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)) or 1.0)])
    return U @ D @ Vt


def extrapolate_T(T_before: np.ndarray, T_last: np.ndarray) -> np.ndarray:
    """The pose one step after ``T_last`` at the motion from ``T_before`` to ``T_last`` (constant velocity),
    its rotation re-orthonormalised: extrapolating pose after pose from its own output multiplies a rotation's
    rounding error by 1 + sqrt(2) each time (a monocular street's keyframes lost their rotations so)."""
    T = T_last @ inv_T(T_before) @ T_last
    T[:3, :3] = nearest_rotation(T[:3, :3])
    return T


def two_view_pose(T_world_base_kf: np.ndarray, T_base_cam: np.ndarray, R_cur_kf: np.ndarray, t_dir_cur_kf: np.ndarray,
                  baseline: float) -> np.ndarray:
    """T_world_base now from the last keyframe's pose and the two-view relative pose of the cameras
    (X_cur = R X_kf + t), the translation direction scaled to ``baseline`` (m, or the run's unit before the scale
    is known)."""
    t_unit = t_dir_cur_kf / max(float(np.linalg.norm(t_dir_cur_kf)), 1e-9)
    T_world_cam = T_world_base_kf @ T_base_cam @ inv_T(make_T(R_cur_kf, t_unit * baseline))
    return T_world_cam @ inv_T(T_base_cam)


def with_tilt_of(T_planar: np.ndarray, T_tilt: np.ndarray) -> np.ndarray:
    """``T_planar`` with the roll and pitch of ``T_tilt``: its position and heading (the yaw of its x axis) kept,
    its rotation that of ``T_tilt`` turned about the world's z axis to that heading."""
    yaw_planar = float(np.arctan2(T_planar[1, 0], T_planar[0, 0]))
    yaw_tilt = float(np.arctan2(T_tilt[1, 0], T_tilt[0, 0]))
    T = np.array(T_planar, dtype=float, copy=True)
    T[:3, :3] = rot_z(yaw_planar - yaw_tilt) @ T_tilt[:3, :3]
    return T


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def rpy_to_R(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Z-Y-X (yaw, pitch, roll) convention used by robots: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def R_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(R[2, 1], R[2, 2]))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def planar_T(x: float, y: float, yaw: float) -> np.ndarray:
    """T of a planar pose: at (x, y, 0), turned by ``yaw`` about z (``make_T(rot_z(yaw), [x, y, 0])``, built in one
    literal: the wheels' buffer makes about 13 a frame)."""
    c, s = float(np.cos(yaw)), float(np.sin(yaw))
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def so3_log(R: np.ndarray) -> np.ndarray:
    cos_a = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    a = np.arccos(cos_a)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if a < 1e-8:
        return 0.5 * w
    if np.pi - a < 1e-6:
        # Near pi: take the axis from the symmetric part.
        M = (R + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(M), 0.0, None))
        k = int(np.argmax(axis))
        axis = M[:, k] / max(np.sqrt(M[k, k]), 1e-12)
        return a * axis / np.linalg.norm(axis)
    return a / (2.0 * np.sin(a)) * w


def so3_exp(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, dtype=float)
    a = np.linalg.norm(w)
    if a < 1e-12:
        return np.eye(3)
    k = w / a
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx


def rotation_angle(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def interpolate_T(T_a: np.ndarray, T_b: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction ``s`` from ``T_a`` (s=0) to ``T_b`` (s=1): slerp rotation, lerp translation."""
    R_ab = T_a[:3, :3].T @ T_b[:3, :3]
    R = T_a[:3, :3] @ so3_exp(s * so3_log(R_ab))
    t = (1.0 - s) * T_a[:3, 3] + s * T_b[:3, 3]
    return make_T(R, t)


def quat_from_R(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        w = 0.25 * s
        x = (m[2, 1] - m[1, 2]) / s
        y = (m[0, 2] - m[2, 0]) / s
        z = (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w = (m[2, 1] - m[1, 2]) / s
        x = 0.25 * s
        y = (m[0, 1] + m[1, 0]) / s
        z = (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w = (m[0, 2] - m[2, 0]) / s
        x = (m[0, 1] + m[1, 0]) / s
        y = 0.25 * s
        z = (m[1, 2] + m[2, 1]) / s
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w = (m[1, 0] - m[0, 1]) / s
        x = (m[0, 2] + m[2, 0]) / s
        y = (m[1, 2] + m[2, 1]) / s
        z = 0.25 * s
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def R_from_quat(q: np.ndarray) -> np.ndarray:
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
