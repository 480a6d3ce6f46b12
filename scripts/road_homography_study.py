"""Study (issue #26 item 2): can the road in front of a car measure the metric scale by region alignment?

For consecutive frames of a KITTI excerpt, the road region in front of the car (the pixels whose rays meet the
plane ``n . X = h`` between ``--zmin`` and ``--zmax`` metres ahead, within ``--xmax`` metres of the camera's
axis) is aligned between the two images through the plane-induced homography ``H = R + s t_dir n^T`` (normalised
coordinates, ``s = |t| / h``): the rotation ``R`` and the translation direction ``t_dir`` are given (ground
truth, or vision's essential matrix on KLT tracks), ``s`` is searched for the best zero-mean normalised
cross-correlation. The scale error is ``s h / |t_true| - 1``.

It prints, per assumed tilt of the road plane (camera pitch against the road, degrees; 0 is the KITTI set-up's
level camera 1.65 m above the road): the median and the spread (MAD) of the per-pair scale errors with ground
truth and with vision's motion, and the alignment's mean best correlation when the tilt is varied over a fixed
region (how well the images themselves tell the tilt).

    python scripts/road_homography_study.py ../shared/data/kitti06_000-050

(The joint tilt-and-scale search of docs/scale_suite.md was run with the functions of this script on every second
pair, a 3-25 m region and tilts -0.5 to 2.5 deg in 0.25 deg steps.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

HEIGHT_M = 1.65  # KITTI: camera 0 above the road


def read_kitti(folder: Path) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """K of camera 0, its poses (N, 4, 4) and the blurred float images."""
    P0 = np.array([float(x) for x in (folder / "calib.txt").read_text().splitlines()[0].split()[1:]]).reshape(3, 4)
    rows = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3] = rows
    images = [cv2.GaussianBlur(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(np.float32), (0, 0), 1.0)
              for p in sorted((folder / "image_0").glob("*.png"))]
    return P0[:, :3], poses, images


def road_normal(tilt_deg: float) -> np.ndarray:
    """Downward road normal in camera 0's frame (y down, z forward), the camera pitched ``tilt_deg`` down."""
    a = np.radians(tilt_deg)
    return np.array([0.0, np.cos(a), np.sin(a)])


def road_region(K: np.ndarray, shape: tuple[int, int], n: np.ndarray, zmin: float, zmax: float, xmax: float):
    """Pixels (every second) and their rays that meet the road within the box ahead."""
    H, W = shape
    v, u = np.mgrid[0:H:2, 0:W:2]
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    ny = n @ rays
    with np.errstate(divide="ignore"):
        X = rays * (HEIGHT_M / ny)
    ok = (ny > 0) & (X[2] >= zmin) & (X[2] <= zmax) & (np.abs(X[0]) <= xmax)
    return u.ravel()[ok].astype(np.float32), v.ravel()[ok].astype(np.float32), rays[:, ok]


def zncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


def correlations(K, I0, I1, R, t_dir, n, region, scales) -> np.ndarray:
    """Correlation of the region of I0 with I1 warped by the plane homography, for each scale s = |t| / h."""
    u, v, rays = region
    a = cv2.remap(I0, u.reshape(1, -1), v.reshape(1, -1), cv2.INTER_LINEAR).ravel()
    out = np.full(len(scales), -1.0)
    for k, s in enumerate(scales):
        x = K @ ((R + s * np.outer(t_dir, n)) @ rays)
        uj, vj = (x[0] / x[2]).astype(np.float32), (x[1] / x[2]).astype(np.float32)
        b = cv2.remap(I1, uj.reshape(1, -1), vj.reshape(1, -1), cv2.INTER_LINEAR, borderValue=-1.0).ravel()
        ok = (b >= 0) & (x[2] > 0)
        if ok.sum() > 200:
            out[k] = zncc(a[ok], b[ok])
    return out


def best_scale(K, I0, I1, R, t_dir, n, region) -> tuple[float, float]:
    """Coarse (log grid 0.02-2) then fine search of s; returns (s, correlation)."""
    coarse = np.exp(np.linspace(np.log(0.02), np.log(2.0), 120))
    c = correlations(K, I0, I1, R, t_dir, n, region, coarse)
    fine = coarse[int(np.argmax(c))] * np.exp(np.linspace(-0.06, 0.06, 41))
    cf = correlations(K, I0, I1, R, t_dir, n, region, fine)
    k = int(np.argmax(cf))
    return float(fine[k]), float(cf[k])


def vision_motion(K, I0, I1) -> tuple[np.ndarray, np.ndarray]:
    """R and the unit t (frame 0 -> 1) from KLT tracks and the essential matrix."""
    g0, g1 = (np.clip(x, 0, 255).astype(np.uint8) for x in (I0, I1))
    p0 = cv2.goodFeaturesToTrack(g0, 1500, 0.01, 8)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(g0, g1, p0, None, winSize=(21, 21), maxLevel=3)
    ok = st.ravel() == 1
    a0, a1 = p0[ok].reshape(-1, 2), p1[ok].reshape(-1, 2)
    E, mask = cv2.findEssentialMat(a0, a1, K, cv2.RANSAC, 0.999, 1.0)
    _, R, t, _ = cv2.recoverPose(E, a0, a1, K, mask=mask)
    return R, t.ravel() / np.linalg.norm(t)


def scale_errors(K, poses, images, tilt_deg, box, vision: bool) -> np.ndarray:
    n = road_normal(tilt_deg)
    region = road_region(K, images[0].shape, n, *box)
    errs = []
    for i in range(len(images) - 1):
        T_c1_c0 = np.linalg.inv(poses[i + 1]) @ poses[i]
        dist = float(np.linalg.norm(T_c1_c0[:3, 3]))
        R, t_dir = vision_motion(K, images[i], images[i + 1]) if vision else (T_c1_c0[:3, :3], T_c1_c0[:3, 3] / dist)
        s, _ = best_scale(K, images[i], images[i + 1], R, t_dir, n, region)
        errs.append(s * HEIGHT_M / dist - 1.0)
    return np.array(errs)


def tilt_observability(K, poses, images, tilts, box) -> list[float]:
    """Mean best correlation over every third pair per assumed tilt, on the region of tilt 0 (fixed pixels)."""
    region = road_region(K, images[0].shape, road_normal(0.0), *box)
    means = []
    for tilt in tilts:
        n, best = road_normal(tilt), []
        for i in range(0, len(images) - 1, 3):
            T_c1_c0 = np.linalg.inv(poses[i + 1]) @ poses[i]
            dist = float(np.linalg.norm(T_c1_c0[:3, 3]))
            scales = dist / HEIGHT_M * np.exp(np.linspace(-0.3, 0.3, 61))
            best.append(correlations(K, images[i], images[i + 1], T_c1_c0[:3, :3], T_c1_c0[:3, 3] / dist, n,
                                     region, scales).max())
        means.append(float(np.mean(best)))
    return means


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="a KITTI excerpt (calib.txt, poses.txt, image_0/)")
    ap.add_argument("--zmin", type=float, default=3.0)
    ap.add_argument("--zmax", type=float, default=10.0)
    ap.add_argument("--xmax", type=float, default=1.5)
    ap.add_argument("--tilts", type=float, nargs="+", default=[-0.5, 0.0, 0.5, 1.0, 1.5])
    args = ap.parse_args()
    K, poses, images = read_kitti(args.folder)
    box = (args.zmin, args.zmax, args.xmax)
    obs = tilt_observability(K, poses, images, args.tilts, box)
    print(f"{args.folder.name}: road {args.zmin:g}-{args.zmax:g} m ahead, +-{args.xmax:g} m; {len(images) - 1} pairs")
    print("| tilt (deg) | scale error, true motion: median / MAD | vision's motion: median / MAD / share > 5% "
          "| mean best correlation (fixed region) |")
    print("|---|---|---|---|")
    for tilt, c in zip(args.tilts, obs):
        e_true = scale_errors(K, poses, images, tilt, box, vision=False)
        e_vis = scale_errors(K, poses, images, tilt, box, vision=True)
        mad = lambda e: float(np.median(np.abs(e - np.median(e))))  # noqa: E731
        print(f"| {tilt:+.2f} | {100 * np.median(e_true):+.1f}% / {100 * mad(e_true):.1f}% "
              f"| {100 * np.median(e_vis):+.1f}% / {100 * mad(e_vis):.1f}% / {np.mean(np.abs(e_vis) > 0.05):.0%} "
              f"| {c:.4f} |")


if __name__ == "__main__":
    main()
