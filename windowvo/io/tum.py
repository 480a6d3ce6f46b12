"""TUM RGB-D loader (``rgb.txt``, ``rgb/``, ``groundtruth.txt``).

Intrinsics from the config's ``camera`` section (TUM does not ship them in the folder); base =
camera with robot axes; ground truth (pose of the camera in the motion-capture world) is
interpolated at the image times, converted with ``T_cam_base`` and re-anchored at the first frame.
TUM is hand-held data: the config turns the planar roll/pitch prior off by default for it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import CameraConfig, Config
from ..errors import SequenceError
from ..geometry import R_from_quat, inv_T, make_T
from .common import anchor, camera_from_config, interp_poses, read_table
from .sequence import Sequence


def load_tum(root: Path, cam_cfg: CameraConfig | None) -> Sequence:
    root = Path(root)
    if not root.is_dir():
        raise SequenceError(f"sequence folder not found: {root}")
    rows = read_table(root / "rgb.txt", 2)
    try:
        times = np.asarray([float(r[0]) for r in rows])
    except ValueError:
        raise SequenceError("rgb.txt: timestamps must be numbers") from None
    images = [root / r[1] for r in rows]
    missing = [p for p in images if not p.is_file()]
    if missing:
        raise SequenceError(f"rgb.txt lists {len(missing)} missing image(s), e.g. {missing[0].name}")
    if np.any(np.diff(times) <= 0):
        raise SequenceError("rgb.txt: timestamps are not strictly increasing")
    warnings: list[str] = []
    cam = camera_from_config(cam_cfg, "tum", warnings)
    gt = None
    if (root / "groundtruth.txt").is_file():
        g = np.asarray([[float(x) for x in r[:8]] for r in read_table(root / "groundtruth.txt", 8)])
        T_w_c = np.stack([make_T(R_from_quat(r[4:8]), r[1:4]) for r in g])
        T_w_c_img, inside = interp_poses(g[:, 0], T_w_c, times)
        if inside.sum() >= 2:
            T_w_b = np.einsum("nij,jk->nik", T_w_c_img[inside], inv_T(cam.T_base_cam))
            gt = anchor(times[inside], T_w_b)
    return Sequence(root, images, times, cam, None, gt, warnings, name=root.name)


def load(cfg: Config) -> Sequence:
    """The loader's entry in the dataset registry (``windowvo.io.load``)."""
    return load_tum(cfg.sequence, cfg.camera)
