"""Study (issue #26): the floor's region measured at ground truth's motion, step by step, against the true lengths.

    python scripts/road_region_at_truth.py FOLDER... [--every N] [--set KEY=VALUE ...] [--normal setup|truth] [--steps]

Each FOLDER is a rendered sequence (the scale suite's cache: camera.yaml, groundtruth.txt, images/) or a KITTI
excerpt (calib.txt, poses.txt, image_0/; camera 0 taken 1.65 m above a level base, as the scale suite does). For each
pair of consecutive frames (every N-th), ``measure_step`` runs with ground truth's rotation and direction on the
floor the set-up assumes (``--normal setup``: the base's z axis) or on the true floor seen from ground truth's
attitude (``--normal truth``: a rocking base's tilt applied), with ``backend.ground.road_region`` as configured
(``--set road_region_key=value``, e.g. ``--set blur_px=0.5``; ``pitch_search_deg=0`` for the length on the assumed
floor alone). Printed per sequence: the steps measured, the measured length over the true one (median, median
absolute deviation, RMS), and the floor's pitch the steps found; with ``--steps`` before it each frame pair's
pitch and length error (``k:pitch/error%``, ``k:-`` where the region measured nothing), to see how they change
along the sequence. The measurement alone, without the estimator: what docs/scale_suite.md's "The region's pitch
search at ground truth's motion" quotes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

from windowvo.backend import road_region as rr
from windowvo.camera import CameraModel
from windowvo.config import RoadRegionConfig
from windowvo.errors import WindowVOError

KITTI_HEIGHT_M = 1.65
R_BASE_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera x right, y down, z ahead


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def load(folder: Path) -> tuple[CameraModel, list[np.ndarray], list[Path]]:
    """The camera (with T_base_cam), ground truth's T_world_base per frame and the images, of either layout."""
    if (folder / "poses.txt").is_file() and (folder / "calib.txt").is_file():
        P = np.array((folder / "calib.txt").read_text().splitlines()[0].split()[1:], float).reshape(3, 4)
        images = sorted((folder / "image_0").glob("*.png"))
        if not images:
            raise WindowVOError(f"{folder}: no images in image_0/")
        h, w = cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE).shape
        T_bc = np.eye(4)
        T_bc[:3, :3], T_bc[2, 3] = R_BASE_CAM, KITTI_HEIGHT_M
        cam = CameraModel(w, h, P[0, 0], P[1, 1], P[0, 2], P[1, 2], T_base_cam=T_bc)
        T_base_cam_inv = np.linalg.inv(T_bc)
        poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
        T_wb = [np.vstack([p, [0, 0, 0, 1]]) @ T_base_cam_inv for p in poses]
        return cam, T_wb, images
    if not (folder / "camera.yaml").is_file() or not (folder / "groundtruth.txt").is_file():
        raise WindowVOError(f"{folder}: neither a KITTI excerpt (calib.txt, poses.txt) nor a rendered sequence "
                            "(camera.yaml, groundtruth.txt)")
    c = yaml.safe_load((folder / "camera.yaml").read_text())
    if c.get("distortion_model", "none") != "none":
        raise WindowVOError(f"{folder}: a distorted camera (this study takes pinhole cameras)")
    T_bc = np.array(c["T_base_cam"], float).reshape(4, 4)
    cam = CameraModel(c["width"], c["height"], c["fx"], c["fy"], c["cx"], c["cy"], T_base_cam=T_bc)
    T_wb = []
    for row in np.loadtxt(folder / "groundtruth.txt", comments="#"):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _quat_matrix(row[4:8]), row[1:4]
        T_wb.append(T)
    return cam, T_wb, sorted((folder / "images").glob("*.png"))


def study(folder: Path, cfg: RoadRegionConfig, every: int, truth_normal: bool, steps: bool = False) -> str:
    cam, T_wb, images = load(folder)
    grid = rr.pixel_grid(cam, cfg.step_px)
    if cfg.pitch_search_deg > 0:  # a step's own pitch search, on its region (``RoadRegionCue``'s)
        cfg = cfg.model_copy(update={"far_heights": cfg.pitch_far_heights})
    ratios, pitches, listing = [], [], []
    up = np.array([0.0, 0.0, 1.0])
    for k in range(1, min(len(images), len(T_wb)), every):
        n_base, offset = up, 0.0  # the floor z = 0 under the base
        if truth_normal:  # the world's up (the floor z = 0) in base k-1's frame, and the floor's offset there
            n_base = T_wb[k - 1][:3, :3].T @ up
            offset = -float(T_wb[k - 1][2, 3])
        n_cam, h = rr.floor_in_camera(cam.T_base_cam, n_base, offset)
        img0, img1 = (rr.smoothed(cv2.imread(str(images[i]), cv2.IMREAD_GRAYSCALE), cfg.blur_px, cfg.normalise_px,
                                   cfg.normalise_floor) for i in (k - 1, k))
        T_wc0, T_wc1 = T_wb[k - 1] @ cam.T_base_cam, T_wb[k] @ cam.T_base_cam
        fit = rr.measure_step(cam, img0, img1, T_wc0, T_wc1, n_cam, h, cfg, grid)
        if fit is not None:
            ratios.append(fit.camera_m / float(np.linalg.norm(T_wc1[:3, 3] - T_wc0[:3, 3])))
            pitches.append(fit.pitch_deg)
        listing.append(f"{k}:-" if fit is None else f"{k}:{fit.pitch_deg:+.2f}/{100 * (ratios[-1] - 1):+.1f}")
    head = f"{folder.name} steps (frame:pitch deg/length error %): {' '.join(listing)}\n" if steps else ""
    if not ratios:
        return f"{head}{folder.name:34s} no step measured"
    e, p = np.asarray(ratios) - 1.0, np.asarray(pitches)
    med, pmed = float(np.median(e)), float(np.median(p))
    return (f"{head}{folder.name:34s} steps {len(e):3d}  length {100 * med:+6.2f}% (MAD {100 * np.median(np.abs(e - med)):.2f}%, "
            f"RMS {100 * np.sqrt(np.mean(e * e)):.2f}%)  pitch {pmed:+.2f} deg (MAD {np.median(np.abs(p - pmed)):.2f})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--every", type=int, default=1, help="every N-th frame pair")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a backend.ground.road_region key (repeatable)")
    ap.add_argument("--normal", choices=["setup", "truth"], default="setup",
                    help="the floor assumed: the set-up's (the base's z) or ground truth's (the rocking applied)")
    ap.add_argument("--steps", action="store_true", help="also each frame pair's pitch and length error")
    a = ap.parse_args(argv)
    try:
        if a.every < 1:
            raise WindowVOError(f"--every must be at least 1 (got {a.every})")
        over: dict = {}
        for kv in a.set:
            key, sep, value = kv.partition("=")
            if not sep:
                raise WindowVOError(f"--set {kv!r}: expected KEY=VALUE")
            over[key.strip()] = yaml.safe_load(value)
        cfg = RoadRegionConfig.model_validate({"enabled": True, **over})
        for folder in a.folders:
            print(study(folder, cfg, a.every, a.normal == "truth", a.steps), flush=True)
    except (WindowVOError, ValueError, OSError) as err:
        print(f"road_region_at_truth.py: error: {' '.join(str(err).split())[:300]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
