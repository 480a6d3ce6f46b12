"""Loaders for standard dataset layouts, all producing a native :class:`Sequence`.

Frames each loader assumes (base = the robot/body frame of ``T_world_base``):

* **kitti** (odometry benchmark: ``image_0/``, ``calib.txt``, ``times.txt``, ``poses.txt``):
  intrinsics from ``P0``; no distortion (rectified). KITTI has no base frame, so the base is
  placed on the road 1.65 m below camera 0 (KITTI set-up), with robot axes (x forward, y left,
  z up): ``T_base_cam`` is the axis change lifted by the camera height, so the ground-plane cue
  works by default. ``poses.txt`` holds ``T_cam0_camk``; ground truth becomes
  ``T_world_base = T_base_cam T_cam0_camk T_cam_base``.
* **tum** (TUM RGB-D: ``rgb.txt``, ``rgb/``, ``groundtruth.txt``): intrinsics from the config's
  ``camera`` section (TUM does not ship them in the folder); base = camera with robot axes;
  ground truth (pose of the camera in the motion-capture world) is interpolated at the image
  times and converted with ``T_cam_base``.
* **euroc** (ASL: ``mav0/cam0/data.csv``, ``mav0/cam0/sensor.yaml``,
  ``mav0/state_groundtruth_estimate0/data.csv``): radtan intrinsics and ``T_BS`` from
  ``sensor.yaml``; base = the body (IMU) frame B, so ``T_base_cam = T_BS``; ground truth is
  ``T_R_B`` directly.
* **folder**: a bare image folder (the ``sequence`` itself or its ``images/``), intrinsics and
  ``T_base_cam`` from the config's ``camera`` section, timestamps from ``fps``.

Every loader re-anchors ground truth so world = base at the first frame. Wheel odometry
can be synthesised from ground truth (``odometry_synthesis`` in the config); the file
header and the run summary then say it is synthetic.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import yaml

from ..camera import CameraModel, DistortionModel
from ..config import CameraConfig, Config, DatasetKind
from ..errors import CalibrationError, SequenceError
from ..geometry import R_BASE_CAM_FORWARD, R_from_quat, inv_T, make_T
from .odometry import WheelOdometry
from .sequence import Sequence, list_images, read_times
from .trajectory import Trajectory

log = logging.getLogger(__name__)

T_BASE_CAM_FORWARD = make_T(R_BASE_CAM_FORWARD, np.zeros(3))
# Height of KITTI's camera 0 above the road (KITTI set-up).
KITTI_CAMERA_HEIGHT_M = 1.65


def _camera_from_config(c: CameraConfig | None, what: str) -> CameraModel:
    if c is None:
        raise CalibrationError(f"dataset '{what}' needs a 'camera' section in the config (width, height, fx, fy, cx, cy)")
    T = np.asarray(c.T_base_cam, float).reshape(4, 4) if c.T_base_cam is not None else T_BASE_CAM_FORWARD
    return CameraModel(c.width, c.height, c.fx, c.fy, c.cx, c.cy, DistortionModel(c.distortion_model),
                       tuple(c.distortion), T)


def _anchor(ts: np.ndarray, T_world_base: np.ndarray) -> Trajectory:
    return Trajectory(ts, T_world_base).anchored()


# ---------------------------------------------------------------------------- KITTI


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
    T_base_cam = make_T(R_BASE_CAM_FORWARD, np.array([0.0, 0.0, KITTI_CAMERA_HEIGHT_M]))
    cam = CameraModel(w, h, P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2], DistortionModel.NONE, (), T_base_cam)
    times = read_times(root / "times.txt", len(images))
    gt = None
    if (root / "poses.txt").is_file():
        T_c0_ck = read_kitti_poses(root / "poses.txt", len(images))
        T_bc = cam.T_base_cam
        gt = _anchor(times, np.einsum("ij,njk,kl->nil", T_bc, T_c0_ck, inv_T(T_bc)))
    return Sequence(root, images, times, cam, None, gt, [], name=root.name)


# ---------------------------------------------------------------------------- TUM RGB-D


def _read_table(path: Path, min_cols: int, sep: str | None = None) -> list[list[str]]:
    if not path.is_file():
        raise SequenceError(f"file not found: {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in (s.split(sep) if sep else s.split())]
        if len(parts) < min_cols:
            raise SequenceError(f"{path.name}:{lineno}: expected at least {min_cols} columns")
        rows.append(parts)
    if not rows:
        raise SequenceError(f"{path.name}: no entries")
    return rows


def _interp_poses(t_src: np.ndarray, T_src: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at times t (slerp/lerp); returns the mask of times inside the source span."""
    from ..geometry import interpolate_T

    inside = (t >= t_src[0]) & (t <= t_src[-1])
    out = np.zeros((len(t), 4, 4))
    for i, ti in enumerate(t):
        if not inside[i]:
            continue
        j = int(np.clip(np.searchsorted(t_src, ti) - 1, 0, len(t_src) - 2))
        s = (ti - t_src[j]) / max(t_src[j + 1] - t_src[j], 1e-12)
        out[i] = interpolate_T(T_src[j], T_src[j + 1], float(np.clip(s, 0, 1)))
    return out, inside


def load_tum(root: Path, cam_cfg: CameraConfig | None) -> Sequence:
    root = Path(root)
    if not root.is_dir():
        raise SequenceError(f"sequence folder not found: {root}")
    rows = _read_table(root / "rgb.txt", 2)
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
    cam = _camera_from_config(cam_cfg, "tum")
    gt = None
    if (root / "groundtruth.txt").is_file():
        g = np.asarray([[float(x) for x in r[:8]] for r in _read_table(root / "groundtruth.txt", 8)])
        T_w_c = np.stack([make_T(R_from_quat(r[4:8]), r[1:4]) for r in g])
        T_w_c_img, inside = _interp_poses(g[:, 0], T_w_c, times)
        if inside.sum() >= 2:
            T_w_b = np.einsum("nij,jk->nik", T_w_c_img[inside], inv_T(cam.T_base_cam))
            gt = _anchor(times[inside], T_w_b)
    return Sequence(root, images, times, cam, None, gt, [], name=root.name)


# ---------------------------------------------------------------------------- EuRoC


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
    rows = _read_table(mav / "cam0" / "data.csv", 2, sep=",")
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
        g = np.asarray([[float(x) for x in r[:8]] for r in _read_table(gt_path, 8, sep=",")])
        tg = g[:, 0] * 1e-9
        # columns: p_RS_R x y z, q_RS w x y z  (body B in world R)
        T_R_B = np.stack([make_T(R_from_quat(r[[5, 6, 7, 4]]), r[1:4]) for r in g])  # w x y z -> x y z w
        T_img, inside = _interp_poses(tg, T_R_B, times)
        if inside.sum() >= 2:
            gt = _anchor(times[inside], T_img[inside])
    return Sequence(root, images, times, cam, None, gt, [], name=root.name)


# ---------------------------------------------------------------------------- plain folder


def load_folder(root: Path, cam_cfg: CameraConfig | None, fps: float) -> Sequence:
    root = Path(root)
    if not root.is_dir():
        raise SequenceError(f"image folder not found: {root}")
    folder = root / "images" if (root / "images").is_dir() else root
    images = list_images(folder)
    cam = _camera_from_config(cam_cfg, "folder")
    times = np.arange(len(images), dtype=float) / fps
    return Sequence(root, images, times, cam, None, None, [f"plain folder: timestamps from fps={fps}"],
                    name=root.name)


# ---------------------------------------------------------------------------- odometry synthesis


def integrate_wheel_odometry(ts: np.ndarray, ds: np.ndarray, dyaw: np.ndarray, *, scale_error: float,
                             yaw_bias_per_m: float, distance_noise: float, yaw_noise: float,
                             rng: np.random.Generator, slip_windows: Iterable[tuple[float, float, float]] = (),
                             comment: str = "") -> WheelOdometry:
    """Dead-reckon wheel odometry from the true planar increments of the base.

    ``ds[i]`` (signed distance along the base's x axis) and ``dyaw[i]`` are the true motion from
    ``ts[i-1]`` to ``ts[i]`` (entry 0 is unused). What the wheels report: the distance scaled by
    ``1 + scale_error`` (and by ``1 + extra`` inside each slip window ``(t0, t1, extra)``) plus a
    random walk of ``distance_noise`` m/sqrt(m); the heading change plus ``yaw_bias_per_m`` rad
    per metre and a random walk of ``yaw_noise`` rad/sqrt(m). Integrated at the mid heading.
    """
    ts = np.asarray(ts, float)
    n = len(ts)
    ds = np.asarray(ds, float)[1:]
    dyaw = np.asarray(dyaw, float)[1:]
    factor = np.full(n - 1, 1.0 + scale_error)
    for t0, t1, extra in slip_windows:
        factor[(ts[1:] >= t0) & (ts[1:] <= t1)] *= 1.0 + extra
    dist = np.abs(ds)
    z = rng.standard_normal((n - 1, 2))  # per step: distance noise, then heading noise
    ds_m = ds * factor + distance_noise * np.sqrt(dist) * z[:, 0]
    dyaw_m = dyaw + yaw_bias_per_m * dist + yaw_noise * np.sqrt(dist) * z[:, 1]
    yaw = np.concatenate([[0.0], np.cumsum(dyaw_m)])
    mid = yaw[:-1] + 0.5 * dyaw_m
    x = np.concatenate([[0.0], np.cumsum(ds_m * np.cos(mid))])
    y = np.concatenate([[0.0], np.cumsum(ds_m * np.sin(mid))])
    return WheelOdometry(ts.copy(), x, y, yaw, comment=comment)


def synthesize_odometry(gt: Trajectory, scale_error: float, yaw_bias_per_m: float, noise: float, seed: int,
                        label: str) -> WheelOdometry:
    """Wheel odometry from ground truth: planar increments of the base with the generator's errors."""
    T = gt.T_world_base
    d = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, 3:] - T[:-1, :3, 3:])[:, :, 0]  # R_prev^T dt
    R_rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    ds = np.concatenate([[0.0], np.hypot(d[:, 0], d[:, 1]) * np.where(d[:, 0] >= 0, 1.0, -1.0)])
    dyaw = np.concatenate([[0.0], np.arctan2(R_rel[:, 1, 0], R_rel[:, 0, 0])])
    comment = (f"{label} wheel odometry synthesised from ground truth: scale_error={scale_error}, "
               f"yaw_bias_per_m={yaw_bias_per_m}, noise={noise}, seed={seed}")
    return integrate_wheel_odometry(gt.timestamps, ds, dyaw, scale_error=scale_error, yaw_bias_per_m=yaw_bias_per_m,
                                    distance_noise=noise, yaw_noise=noise, rng=np.random.default_rng(seed),
                                    comment=comment)


def load(cfg: Config) -> Sequence:
    """Load the configured dataset (any kind but native, which ``load_native`` handles)."""
    kind = cfg.dataset
    if kind is DatasetKind.KITTI:
        seq = load_kitti(cfg.sequence)
    elif kind is DatasetKind.TUM:
        seq = load_tum(cfg.sequence, cfg.camera)
    elif kind is DatasetKind.EUROC:
        seq = load_euroc(cfg.sequence)
    elif kind is DatasetKind.FOLDER:
        seq = load_folder(cfg.sequence, cfg.camera, cfg.fps)
    elif kind is DatasetKind.ROSBAG:
        from .rosbag import load_rosbag

        seq = load_rosbag(cfg.sequence, cfg.rosbag, cfg.camera)
    elif kind is DatasetKind.VIDEO:
        from .video import load_video

        seq = load_video(cfg.sequence, cfg.camera, cfg.fps)
    else:
        from .sequence import load_native

        seq = load_native(cfg.sequence, cfg.fps)
    return finish_sequence(seq, cfg)


# Layouts recorded by hand-held cameras (tum) or drones (euroc): their base is not a ground
# robot's level, z-up base, so the priors that assume one are off unless the config sets them.
NOT_GROUND_ROBOT = (DatasetKind.TUM, DatasetKind.EUROC)


def apply_layout_defaults(cfg: Config) -> list[str]:
    """Defaults that depend on the layout; an explicit setting in the config always wins.

    Returns the log lines of what changed (also logged at INFO). ``model_fields_set`` holds
    the keys the config (file or overrides) set, so a default can be told from a choice.
    """
    notes: list[str] = []
    pp = cfg.backend.planar_prior
    if cfg.dataset in NOT_GROUND_ROBOT and pp.enabled and "enabled" not in pp.model_fields_set:
        pp.enabled = False
        notes.append(f"dataset '{cfg.dataset.value}' is hand-held or drone data (no level, z-up base): the planar "
                     "roll/pitch prior is off; set backend.planar_prior.enabled=true to use it")
    for note in notes:
        log.info("%s", note)
    return notes


def finish_sequence(seq: Sequence, cfg: Config) -> Sequence:
    """Apply config-level options common to every loader (layout defaults, odometry synthesis)."""
    apply_layout_defaults(cfg)
    osyn = cfg.odometry_synthesis
    if osyn.enabled and seq.odometry is None:
        if seq.groundtruth is None:
            raise SequenceError("odometry_synthesis needs ground truth, and this sequence has none")
        seq.odometry = synthesize_odometry(seq.groundtruth, osyn.scale_error, osyn.yaw_bias_per_m, osyn.noise,
                                           osyn.seed, "synthetic")
        seq.warnings.append("wheel odometry is SYNTHETIC (made from ground truth with errors)")
    return seq
