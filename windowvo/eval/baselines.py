"""Baselines that windowvo is measured against, computed on the same sequence.

* **wheel odometry alone** (see ``app.wheel_only_trajectory``),
* **frame-to-frame essential-matrix chaining** (the textbook monocular VO loop): ORB features,
  brute-force Hamming matching with a ratio test, essential matrix by RANSAC, pose recovery,
  translation scaled by the wheel distance driven between the two frames, composed.
"""

from __future__ import annotations

import time
from collections.abc import Sequence as Sequence_
from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import inv_T, make_T
from ..io.sequence import Sequence
from ..io.trajectory import Trajectory


@dataclass
class BaselineRun:
    trajectory: Trajectory
    wall_s: float
    n_frames: int
    n_failed_steps: int

    @property
    def fps(self) -> float:
        return self.n_frames / self.wall_s if self.wall_s > 0 else 0.0


def essential_chaining(seq: Sequence, max_frames: int | None = None, n_features: int = 1000,
                       ratio: float = 0.75, ransac_px: float = 1.0) -> BaselineRun:
    """Frame-to-frame VO scaled by wheel distance; steps that fail keep the wheels' motion."""
    if seq.odometry is None:
        raise ValueError("essential-matrix chaining needs wheel odometry for its scale")
    cam = seq.camera
    orb = cv2.ORB.create(nfeatures=n_features)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    T_bc, T_cb = cam.T_base_cam, inv_T(cam.T_base_cam)
    poses = [np.eye(4)]
    times = [float(seq.timestamps[0])]
    failed = 0
    t0 = time.perf_counter()
    prev_kp: Sequence_[cv2.KeyPoint] = ()
    prev_des: np.ndarray | None = None
    prev_t = float(seq.timestamps[0])
    for i in range(n):
        try:
            img = seq.read_image(i)
        except Exception:
            continue
        kp, des = orb.detectAndCompute(img, None)
        t = float(seq.timestamps[i])
        if prev_des is not None:
            T_step = None
            if des is not None and len(kp) >= 8 and len(prev_kp) >= 8:
                pairs = bf.knnMatch(prev_des, des, k=2)
                good = [m for m, *rest in (p for p in pairs if len(p) == 2) if m.distance < ratio * rest[0].distance]
                if len(good) >= 8:
                    p1 = np.array([prev_kp[m.queryIdx].pt for m in good], dtype=np.float64)
                    p2 = np.array([kp[m.trainIdx].pt for m in good], dtype=np.float64)
                    x1 = cam.undistort_normalized(p1)
                    x2 = cam.undistort_normalized(p2)
                    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                                   threshold=ransac_px / cam.fx)
                    if E is not None and E.shape == (3, 3):
                        ok, R, tvec, _ = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask)
                        if ok >= 8:
                            dist = seq.odometry.distance(prev_t, t)
                            # X_cur = R X_prev + t  ->  T_camprev_camcur = inv([R | t])
                            T_cur_prev = make_T(R, tvec.ravel() / max(float(np.linalg.norm(tvec)), 1e-12) * dist)
                            T_step = T_bc @ inv_T(T_cur_prev) @ T_cb
            if T_step is None:
                failed += 1
                T_step = seq.odometry.delta(prev_t, t)
            poses.append(poses[-1] @ T_step)
            times.append(t)
        prev_kp, prev_des, prev_t = kp, des, t
    wall = time.perf_counter() - t0
    return BaselineRun(Trajectory(np.asarray(times), np.stack(poses)), wall, n, failed)
