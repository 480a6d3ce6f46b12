"""KITTI odometry benchmark loader (``image_0/``, ``calib.txt``, ``times.txt``, ``poses.txt``).

Intrinsics from ``P0``; no distortion (rectified). KITTI has no base frame, so the base is placed on
the road 1.65 m below camera 0 (KITTI set-up), with robot axes (x forward, y left, z up):
``T_base_cam`` is the axis change lifted by the camera height, so the ground-plane cue works by
default. ``poses.txt`` holds ``T_cam0_camk``; ground truth becomes
``T_world_base = T_base_cam T_cam0_camk T_cam_base``, re-anchored at the first frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import CameraModel, DistortionModel
from ..config import Config
from ..errors import CalibrationError, SequenceError
from .common import anchor
from .sequence import Sequence, list_images, read_times
from .trajectory import kitti_cam0_to_base, kitti_T_base_cam0

# The KITTI convention (base on the road 1.65 m below camera 0, robot axes) is shared with the evaluation's
# reader of poses.txt: KITTI_CAMERA_HEIGHT_M, kitti_T_base_cam0, kitti_cam0_to_base in io/trajectory.py.


def read_kitti_calib(path: Path) -> tuple[np.ndarray, float]:
    """P0 as 3x4 and the stereo baseline (m) from P1, if present."""
    if not path.is_file():
        raise CalibrationError(f"KITTI calibration not found: {path}")
    P = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if ":" not in line:
            continue
        name, vals = line.split(":", 1)
        try:
            nums = [float(x) for x in vals.split()]
        except ValueError:
            raise CalibrationError(f"{path.name}:{lineno}: not a number") from None
        if name.strip() in ("P0", "P1"):
            if len(nums) != 12:
                raise CalibrationError(f"{path.name}:{lineno}: {name.strip()} needs 12 numbers, got {len(nums)}")
            P[name.strip()] = np.asarray(nums).reshape(3, 4)
    if "P0" not in P:
        raise CalibrationError(f"{path.name}: no 'P0:' line")
    baseline = float(-P["P1"][0, 3] / P["P1"][0, 0]) if "P1" in P else float("nan")
    return P["P0"], baseline


def read_kitti_poses(path: Path, n: int) -> np.ndarray:
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            v = [float(x) for x in line.split()]
        except ValueError:
            raise SequenceError(f"{path.name}:{lineno}: not a number") from None
        if len(v) != 12:
            raise SequenceError(f"{path.name}:{lineno}: expected 12 numbers (3x4 pose), got {len(v)}")
        T = np.eye(4)
        T[:3, :] = np.asarray(v).reshape(3, 4)
        rows.append(T)
    if len(rows) != n:
        raise SequenceError(f"{path.name} has {len(rows)} poses but image_0/ has {n} frames")
    return np.stack(rows)


def load_kitti(root: Path) -> Sequence:
    root = Path(root)
    if not root.is_dir():
        raise SequenceError(f"sequence folder not found: {root}")
    images = list_images(root / "image_0")
    P0, _ = read_kitti_calib(root / "calib.txt")
    import cv2

    first = cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE)
    if first is None:
        raise SequenceError(f"cannot read {images[0]}")
    h, w = first.shape
    # The base lies on the road below camera 0, with robot axes (KITTI set-up: the camera is 1.65 m up).
    T_base_cam = kitti_T_base_cam0()
    cam = CameraModel(w, h, P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2], DistortionModel.NONE, (), T_base_cam)
    times = read_times(root / "times.txt", len(images))
    gt = None
    if (root / "poses.txt").is_file():
        gt = anchor(times, kitti_cam0_to_base(read_kitti_poses(root / "poses.txt", len(images))))
    return Sequence(root, images, times, cam, None, gt, [], name=root.name)


def load(cfg: Config) -> Sequence:
    """The loader's entry in the dataset registry (``windowvo.io.load``)."""
    return load_kitti(cfg.sequence)
