"""Helpers every dataset loader shares: the default camera mounting, a camera from the config's
``camera`` section, re-anchoring ground truth (world = base at the first frame), pose interpolation
at image times, and whitespace/CSV tables."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..camera import CameraModel, DistortionModel
from ..config import CameraConfig
from ..errors import CalibrationError, SequenceError
from ..geometry import R_BASE_CAM_FORWARD, interpolate_T, make_T
from .trajectory import Trajectory

log = logging.getLogger(__name__)

# A camera at the base origin looking forward (robot axes x forward, y left, z up; camera x right, y down, z forward).
T_BASE_CAM_FORWARD = make_T(R_BASE_CAM_FORWARD, np.zeros(3))


# Said once, when a loader builds the camera of a ``camera`` section without T_base_cam (the default mounting).
DEFAULT_MOUNTING_WARNING = ("camera.T_base_cam missing: camera assumed at the base origin, height 0, looking forward, "
                            "so the floor cue is off (unless backend.ground.camera_height_m is set); set "
                            "camera.T_base_cam (16 numbers, row major: the camera's pose in the base frame)")


def camera_from_config(c: CameraConfig | None, what: str, warnings: list[str] | None = None) -> CameraModel:
    """The camera of the config's ``camera`` section (``what``: the dataset kind, for the message).

    Without ``T_base_cam`` the camera is at the base origin looking forward (height 0: no floor cue), and
    :data:`DEFAULT_MOUNTING_WARNING` says so: appended to ``warnings`` (a sequence's, printed by the job)
    when given, else logged here."""
    if c is None:
        raise CalibrationError(f"dataset '{what}' needs a 'camera' section in the config (width, height, fx, fy, cx, cy)")
    if c.T_base_cam is None:
        if warnings is not None:
            warnings.append(DEFAULT_MOUNTING_WARNING)
        else:
            log.warning("%s", DEFAULT_MOUNTING_WARNING)
    T = np.asarray(c.T_base_cam, float).reshape(4, 4) if c.T_base_cam is not None else T_BASE_CAM_FORWARD
    return CameraModel(c.width, c.height, c.fx, c.fy, c.cx, c.cy, DistortionModel(c.distortion_model),
                       tuple(c.distortion), T)


def anchor(ts: np.ndarray, T_world_base: np.ndarray) -> Trajectory:
    """Ground truth re-anchored so that world = base at the first frame."""
    return Trajectory(ts, T_world_base).anchored()


def read_table(path: Path, min_cols: int, sep: str | None = None) -> list[list[str]]:
    """Rows of a whitespace (or ``sep``) separated table; ``#`` comments and blank lines skipped."""
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


def interp_poses(t_src: np.ndarray, T_src: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at times t (slerp/lerp); returns the mask of times inside the source span."""
    inside = (t >= t_src[0]) & (t <= t_src[-1])
    out = np.zeros((len(t), 4, 4))
    for i, ti in enumerate(t):
        if not inside[i]:
            continue
        j = int(np.clip(np.searchsorted(t_src, ti) - 1, 0, len(t_src) - 2))
        s = (ti - t_src[j]) / max(t_src[j + 1] - t_src[j], 1e-12)
        out[i] = interpolate_T(T_src[j], T_src[j + 1], float(np.clip(s, 0, 1)))
    return out, inside
