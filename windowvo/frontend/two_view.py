"""Two-view geometry against the last keyframe: essential-matrix RANSAC (OpenCV, five-point), pose recovery
with cheirality, and the rotation-compensated parallax the gates judge."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class TwoViewResult:
    inlier_mask: np.ndarray  # (N,) bool, over the common tracks
    E: np.ndarray | None = None
    R_cur_kf: np.ndarray | None = None  # rotation taking kf-camera vectors into the current camera
    t_cur_kf: np.ndarray | None = None  # unit translation direction (current camera frame)
    cheirality_ratio: float = 1.0
    rot_comp_parallax_px: float = 0.0


def essential_ransac(xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float, threshold_px: float,
                     confidence: float) -> TwoViewResult:
    """Essential matrix by USAC (RANSAC family) between normalised points; marks the outliers."""
    n = len(xn_kf)
    if n < 8:
        return TwoViewResult(np.ones(n, bool))
    E, mask = cv2.findEssentialMat(xn_kf, xn_cur, np.eye(3), method=cv2.USAC_DEFAULT, prob=confidence,
                                   threshold=threshold_px / focal)
    if E is None or mask is None or E.shape != (3, 3):
        return TwoViewResult(np.ones(n, bool))
    return TwoViewResult(mask.ravel().astype(bool), E)


def recover_relative_pose(res: TwoViewResult, xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float) -> TwoViewResult:
    """Relative pose from E with the cheirality check, and the rotation-compensated parallax."""
    inl = res.inlier_mask
    if res.E is None or inl.sum() < 5:
        return res
    _, R, t, _ = cv2.recoverPose(res.E, xn_kf[inl], xn_cur[inl], np.eye(3))
    res.R_cur_kf, res.t_cur_kf = R, t.ravel()
    res.cheirality_ratio = cheirality_share(R, t.ravel(), xn_kf[inl], xn_cur[inl])
    res.rot_comp_parallax_px = rotation_compensated_parallax(xn_kf[inl], xn_cur[inl], focal)
    return res


def rotation_compensated_parallax(xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float) -> float:
    """Median angle (as pixels at the focal length) left after the best pure rotation.

    The rotation is fitted to the bearing vectors directly (orthogonal Procrustes), so the
    measure does not depend on decomposing E, which is degenerate without translation.
    """
    a = np.concatenate([xn_kf, np.ones((len(xn_kf), 1))], axis=1)
    b = np.concatenate([xn_cur, np.ones((len(xn_cur), 1))], axis=1)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt  # b ~ R a
    cosang = np.clip(np.einsum("ij,ij->i", a @ R.T, b), -1.0, 1.0)
    return float(np.median(np.arccos(cosang)) * focal)


def cheirality_share(R: np.ndarray, t: np.ndarray, xn_kf: np.ndarray, xn_cur: np.ndarray,
                     min_angle_deg: float = 0.3) -> float:
    """Share of triangulable correspondences (ray angle above ``min_angle_deg``) that lie in
    front of both cameras. Points too far to triangulate count neither way, so a scene of
    mostly distant points (a highway) is not mistaken for a cheirality failure."""
    a = np.concatenate([xn_kf, np.ones((len(xn_kf), 1))], axis=1) @ R.T  # kf rays in the current frame
    b = np.concatenate([xn_cur, np.ones((len(xn_cur), 1))], axis=1)
    # Solve l_b * b - l_a * a = t for the two depths, per point (2x2 normal equations).
    aa = np.einsum("ij,ij->i", a, a)
    bb = np.einsum("ij,ij->i", b, b)
    ab = np.einsum("ij,ij->i", a, b)
    at = a @ t
    bt = b @ t
    det = aa * bb - ab * ab
    cos = ab / np.sqrt(aa * bb)
    usable = (det > 1e-12) & (cos < np.cos(np.radians(min_angle_deg)))
    if not usable.any():
        return 1.0
    la = (ab * bt - bb * at) / np.where(usable, det, 1.0)
    lb = (aa * bt - ab * at) / np.where(usable, det, 1.0)
    good = (la > 0) & (lb > 0) & usable
    return float(good.sum()) / float(usable.sum())


def two_view_geometry(xn_kf: np.ndarray, xn_cur: np.ndarray, focal: float, threshold_px: float,
                      confidence: float) -> TwoViewResult:
    """RANSAC and relative pose in one call."""
    return recover_relative_pose(essential_ransac(xn_kf, xn_cur, focal, threshold_px, confidence), xn_kf, xn_cur, focal)
