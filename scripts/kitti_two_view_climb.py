"""Study (issue #26): does a plain two-view estimate see a KITTI excerpt's steps climb as ground truth does?

``ground.mount_from_motion`` learns the camera's pitch against its floor from the climb of each keyframe step, as the
front end's essential matrix gives it, and the floor's region needs that pitch to a tenth of a degree. On the KITTI
excerpts the front end's climbs are lower than ground truth's (docs/scale_suite.md). This script asks whether that is
the front end's: it estimates each pair of frames ``gap`` apart with plain OpenCV, independent of windowvo (Shi-Tomasi
corners, forward-backward KLT, ``findEssentialMat`` with RANSAC or LMedS, ``recoverPose``; also the translation
refitted to every inlier for the RANSAC rotation, and RANSAC on the corners above or below the principal point only),
and prints each estimator's climb error against ground truth's camera poses (``poses.txt``): median, mean, spread.

    python scripts/kitti_two_view_climb.py ../shared/data/kitti01_000-050 ../shared/data/kitti06_000-050 [--gap 1]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np


def climb_deg(c: np.ndarray) -> float:
    """The climb of a step whose end lies at ``c`` in the camera frame of its start (x right, y down, z forward)."""
    return float(np.degrees(np.arctan2(-c[1], c[2])))


def tracked_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners of ``a`` and where KLT finds them in ``b``, kept when the backward flow returns within 0.5 px."""
    p0 = cv2.goodFeaturesToTrack(a, 1500, 0.005, 7)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(21, 21), maxLevel=3)
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, winSize=(21, 21), maxLevel=3)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(pb - p0, axis=2).ravel() < 0.5)
    return p0[ok].reshape(-1, 2), p1[ok].reshape(-1, 2)


def two_view(x0: np.ndarray, x1: np.ndarray, K: np.ndarray, method: int):
    """(R, t, inlier mask) of the essential matrix by ``method`` and ``recoverPose``; None when it finds none."""
    E, m = cv2.findEssentialMat(x0, x1, K, method=method, prob=0.999, threshold=0.5)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, m2 = cv2.recoverPose(E, x0, x1, K, mask=m.copy())
    return R, t.ravel(), m2.ravel() > 0


def refit_translation(x0: np.ndarray, x1: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The translation direction given the rotation: the least-squares null vector of the epipolar constraints."""
    h0 = np.c_[cv2.undistortPoints(x0.reshape(-1, 1, 2), K, None).reshape(-1, 2), np.ones(len(x0))]
    h1 = np.c_[cv2.undistortPoints(x1.reshape(-1, 1, 2), K, None).reshape(-1, 2), np.ones(len(x1))]
    _, _, Vt = np.linalg.svd(np.cross((R @ h0.T).T, h1))
    return Vt[-1] * np.sign(Vt[-1] @ t)


def study(folder: Path, gap: int) -> dict[str, list[float]]:
    K = np.array(next(line.split()[1:] for line in (folder / "calib.txt").read_text().splitlines()
                      if line.startswith("P0")), float).reshape(3, 4)[:, :3]
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    images = [cv2.imread(str(folder / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(len(poses))]
    errors: dict[str, list[float]] = {k: [] for k in ("RANSAC", "LMedS", "RANSAC, t refitted", "upper half",
                                                      "lower half")}
    for i in range(len(poses) - gap):
        j = i + gap
        x0, x1 = tracked_pairs(images[i], images[j])
        gt = climb_deg(poses[i][:, :3].T @ (poses[j][:, 3] - poses[i][:, 3]))
        lmeds = two_view(x0, x1, K, cv2.LMEDS)
        if lmeds is not None:
            errors["LMedS"].append(climb_deg(-lmeds[0].T @ lmeds[1]) - gt)
        got = two_view(x0, x1, K, cv2.RANSAC)
        if got is None:
            continue
        R, t, inl = got
        errors["RANSAC"].append(climb_deg(-R.T @ t) - gt)
        errors["RANSAC, t refitted"].append(climb_deg(-R.T @ refit_translation(x0[inl], x1[inl], K, R, t)) - gt)
        for name, part in (("upper half", x0[:, 1] < K[1, 2]), ("lower half", x0[:, 1] >= K[1, 2])):
            sub = two_view(x0[inl & part], x1[inl & part], K, cv2.RANSAC) if (inl & part).sum() > 20 else None
            if sub is not None:
                errors[name].append(climb_deg(-sub[0].T @ sub[1]) - gt)
    return errors


def excerpt_problem(folder: Path, gap: int) -> str | None:
    """Why ``folder`` is no KITTI excerpt this study can read (None: it is)."""
    if not (folder / "calib.txt").is_file() or not (folder / "poses.txt").is_file():
        return "no calib.txt and poses.txt (a KITTI excerpt)"
    try:
        n = len(np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4))
    except ValueError as err:
        return f"poses.txt is not 12 numbers a line ({err})"
    if n <= gap:
        return f"{n} poses: no two frames {gap} apart"
    missing = [i for i in range(n) if not (folder / "image_0" / f"{i:06d}.png").is_file()]
    if missing:
        return f"image_0/{missing[0]:06d}.png is missing ({len(missing)} of {n} frames)"
    unreadable = [i for i in range(n) if cv2.imread(str(folder / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
                  is None]
    return f"image_0/{unreadable[0]:06d}.png cannot be decoded" if unreadable else None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+", type=Path, help="KITTI excerpts (image_0/, calib.txt, poses.txt)")
    p.add_argument("--gap", type=int, default=1, help="frames between the two views (default 1)")
    a = p.parse_args(argv)
    if a.gap < 1:
        print(f"kitti_two_view_climb: error: --gap must be at least 1 (got {a.gap})", file=sys.stderr)
        return 2
    for folder in a.folders:
        problem = excerpt_problem(folder, a.gap)
        if problem:
            print(f"kitti_two_view_climb: error: {folder}: {problem}", file=sys.stderr)
            return 2
        print(f"{folder.name}: climb of each step, two-view estimate less ground truth's (deg), frames {a.gap} apart")
        for name, errs in study(folder, a.gap).items():
            e = np.asarray(errs)
            if len(e):
                print(f"  {name:20s} pairs {len(e):3d}  median {np.median(e):+.3f}  mean {e.mean():+.3f}  "
                      f"std {e.std():.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
