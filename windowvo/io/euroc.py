"""EuRoC (ASL) loader (``mav0/cam0/data.csv``, ``mav0/cam0/sensor.yaml``,
``mav0/state_groundtruth_estimate0/data.csv``).

Radtan (or equidistant) intrinsics and ``T_BS`` from ``sensor.yaml``; base = the body (IMU) frame B,
so ``T_base_cam = T_BS``; ground truth is ``T_R_B``, interpolated at the image times and re-anchored.
EuRoC is drone data: the config turns the planar roll/pitch prior off by default for it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from ..camera import CameraModel, DistortionModel
from ..config import Config
from ..errors import CalibrationError, SequenceError
from ..geometry import R_from_quat, make_T
from .common import anchor, interp_poses, read_table
from .sequence import Sequence


def read_euroc_sensor(path: Path) -> CameraModel:
    if not path.is_file():
        raise CalibrationError(f"EuRoC sensor.yaml not found: {path}")
    text = path.read_text()
    try:
        d = yaml.safe_load(text.replace("%YAML:1.0", ""))
    except yaml.YAMLError:
        raise CalibrationError(f"{path.name} is not valid YAML") from None
    try:
        fu, fv, cu, cv = (float(x) for x in d["intrinsics"])
        w, h = (int(x) for x in d["resolution"])
        dist = tuple(float(x) for x in d.get("distortion_coefficients", []))
        T = d["T_BS"]
        T = np.asarray(T["data"] if isinstance(T, dict) else T, float).reshape(4, 4)
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(f"{path.name}: needs intrinsics [fu, fv, cu, cv], resolution [w, h], T_BS") from None
    model = str(d.get("distortion_model", "radial-tangential")).lower()
    dm = DistortionModel.EQUIDISTANT if "equi" in model or "fisheye" in model else DistortionModel.RADTAN
    if not dist:
        dm = DistortionModel.NONE
    return CameraModel(w, h, fu, fv, cu, cv, dm, dist, T)


def load_euroc(root: Path) -> Sequence:
    root = Path(root)
    mav = root / "mav0" if (root / "mav0").is_dir() else root
    if not (mav / "cam0").is_dir():
        raise SequenceError(f"not an EuRoC folder (no mav0/cam0): {root}")
    rows = read_table(mav / "cam0" / "data.csv", 2, sep=",")
    try:
        t_ns = np.asarray([int(r[0]) for r in rows], dtype=np.int64)
    except ValueError:
        raise SequenceError("cam0/data.csv: timestamps must be integers (ns)") from None
    times = t_ns.astype(float) * 1e-9
    images = [mav / "cam0" / "data" / r[1] for r in rows]
    missing = [p for p in images if not p.is_file()]
    if missing:
        raise SequenceError(f"cam0/data.csv lists {len(missing)} missing image(s), e.g. {missing[0].name}")
    cam = read_euroc_sensor(mav / "cam0" / "sensor.yaml")
    gt = None
    gt_path = mav / "state_groundtruth_estimate0" / "data.csv"
    if gt_path.is_file():
        g = np.asarray([[float(x) for x in r[:8]] for r in read_table(gt_path, 8, sep=",")])
        tg = g[:, 0] * 1e-9
        # columns: p_RS_R x y z, q_RS w x y z  (body B in world R)
        T_R_B = np.stack([make_T(R_from_quat(r[[5, 6, 7, 4]]), r[1:4]) for r in g])  # w x y z -> x y z w
        T_img, inside = interp_poses(tg, T_R_B, times)
        if inside.sum() >= 2:
            gt = anchor(times[inside], T_img[inside])
    return Sequence(root, images, times, cam, None, gt, [], name=root.name)


def load(cfg: Config) -> Sequence:
    """The loader's entry in the dataset registry (``windowvo.io.load``)."""
    return load_euroc(cfg.sequence)
