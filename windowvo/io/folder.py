"""Plain image-folder loader: the ``sequence`` itself or its ``images/``; intrinsics and
``T_base_cam`` from the config's ``camera`` section, timestamps from ``fps``; no ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import CameraConfig, Config
from ..errors import SequenceError
from .common import camera_from_config
from .sequence import Sequence, list_images


def load_folder(root: Path, cam_cfg: CameraConfig | None, fps: float) -> Sequence:
    root = Path(root)
    if not root.is_dir():
        raise SequenceError(f"image folder not found: {root}")
    folder = root / "images" if (root / "images").is_dir() else root
    images = list_images(folder)
    warnings = [f"plain folder: timestamps from fps={fps}"]
    cam = camera_from_config(cam_cfg, "folder", warnings)
    times = np.arange(len(images), dtype=float) / fps
    return Sequence(root, images, times, cam, None, None, warnings, name=root.name)


def load(cfg: Config) -> Sequence:
    """The loader's entry in the dataset registry (``windowvo.io.load``)."""
    return load_folder(cfg.sequence, cfg.camera, cfg.fps)
