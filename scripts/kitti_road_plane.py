"""Study (issue #26): where is the road under a KITTI excerpt's camera 0, measured without the VO?

The KITTI excerpts hold the right camera too, so the road can be measured by stereo, independently of the
odometry and of the ground truth: block matching (``cv2.StereoBM``) between ``image_0`` and ``image_1``, the
pixels below the horizon within ``--half-width`` pixels of the principal point whose depth is ``--zmin`` to
``--zmax`` metres, a RANSAC plane through them (``--inlier-m``), refined by least squares on its inliers. Printed per
frame (every ``--every``): camera 0's height above the plane (the distance from its centre), the plane's pitch
and roll in the camera frame, and the inlier share; then the median over the frames.

    python scripts/kitti_road_plane.py ../shared/data/kitti06_000-050 ../shared/data/kitti01_000-050

The numbers of docs/scale_suite.md ("Where the floor is used, and what it knows") are this script's, ``--every 5``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import cv2
import numpy as np


def projection_matrices(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = {line.split(":")[0]: np.array(line.split(":")[1].split(), float).reshape(3, 4)
            for line in (folder / "calib.txt").read_text().splitlines() if ":" in line}
    return rows["P0"], rows["P1"]


def road_points(left: np.ndarray, right: np.ndarray, P0: np.ndarray, P1: np.ndarray, a) -> np.ndarray:
    """3-D points (camera 0 frame: x right, y down, z forward) of the road region, every second pixel."""
    fx, cx, cy = P0[0, 0], P0[0, 2], P0[1, 2]
    baseline = -P1[0, 3] / P1[0, 0]
    disp = cv2.StereoBM_create(numDisparities=96, blockSize=15).compute(left, right).astype(np.float32) / 16.0
    v, u = np.mgrid[0:left.shape[0]:2, 0:left.shape[1]:2]
    d = disp[0:left.shape[0]:2, 0:left.shape[1]:2]
    m = (d > 3) & (v > cy + 30) & (np.abs(u - cx) < a.half_width)
    z = fx * baseline / d[m]
    pts = np.stack([(u[m] - cx) * z / fx, (v[m] - cy) * z / fx, z], axis=1)
    return pts[(z > a.zmin) & (z < a.zmax)]


def fit_plane(pts: np.ndarray, inlier_m: float, seed: int = 0) -> tuple[np.ndarray, float, float]:
    """Normal (pointing down, +y), distance from the camera centre, inlier share."""
    rng = np.random.default_rng(seed)
    best = np.zeros(len(pts), bool)
    for _ in range(200):
        s = pts[rng.integers(0, len(pts), 3)]
        n = np.cross(s[1] - s[0], s[2] - s[0])
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        inl = np.abs(pts @ n - n @ s[0]) < inlier_m
        if inl.sum() > best.sum():
            best = inl
    q = pts[best]
    c = q.mean(axis=0)
    n = np.linalg.svd(q - c)[2][2]
    n = n if n[1] > 0 else -n
    return n, float(n @ c), float(best.mean())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+", type=Path, help="KITTI excerpt folders (image_0, image_1, calib.txt)")
    p.add_argument("--every", type=int, default=5, help="measure every N-th frame")
    p.add_argument("--zmin", type=float, default=4.0)
    p.add_argument("--zmax", type=float, default=18.0)
    p.add_argument("--half-width", type=float, default=200.0, help="pixels either side of the principal point")
    p.add_argument("--inlier-m", type=float, default=0.05)
    a = p.parse_args(argv)
    for folder in a.folders:
        if not (folder / "image_1").is_dir() or not (folder / "calib.txt").is_file():
            print(f"kitti_road_plane: error: {folder} holds no image_1/ and calib.txt (a KITTI stereo excerpt)",
                  file=sys.stderr)
            return 2
        P0, P1 = projection_matrices(folder)
        frames = sorted((folder / "image_0").glob("*.png"))
        heights, pitches, rolls = [], [], []
        print(f"{folder.name}: camera 0 above the road plane (stereo, {a.zmin:.0f}-{a.zmax:.0f} m ahead)")
        for f in frames[:: a.every]:
            left = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            right = cv2.imread(str(folder / "image_1" / f.name), cv2.IMREAD_GRAYSCALE)
            n, h, share = fit_plane(road_points(left, right, P0, P1, a), a.inlier_m)
            pitch, roll = np.degrees(np.arctan2(n[2], n[1])), np.degrees(np.arctan2(n[0], n[1]))
            heights.append(h)
            pitches.append(pitch)
            rolls.append(roll)
            print(f"  {f.stem}: height {h:.3f} m, pitch {pitch:+.2f} deg, roll {roll:+.2f} deg, inliers {share:.2f}")
        print(f"  median: height {statistics.median(heights):.3f} m (min {min(heights):.3f}, max {max(heights):.3f}), "
              f"pitch {statistics.median(pitches):+.2f} deg, roll {statistics.median(rolls):+.2f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
