"""Video files as input (``dataset: video``): mp4, mkv, avi, ... read with ``cv2.VideoCapture``.

``sequence:`` is the video file. Intrinsics and ``T_base_cam`` come from the config's
``camera:`` section. Timestamps come from the container (``CAP_PROP_POS_MSEC`` of each frame,
seconds from the start of the video); when the container has none, from its frame rate, else
from the config's ``fps``.

Wheel odometry and ground truth are optional files beside the video, on the video's clock
(seconds from its first frame): ``<stem>.odometry.csv`` and ``<stem>.groundtruth.txt`` for
the video ``<stem>.mp4`` (so several videos can share a folder), else ``odometry.csv`` and
``groundtruth.txt`` in the same folder. Formats as in the native layout.

Frames are decoded on demand by a forward reader (:class:`VideoFrameSource`); only the
timestamps are collected upfront (one pass of ``grab()``, no colour conversion), so memory
stays flat for a video of any length.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from ..config import CameraConfig, Config
from ..errors import FrameError, SequenceError
from .common import anchor, camera_from_config, interp_poses
from .odometry import read_odometry_csv
from .sequence import StreamedSequence, check_odometry_overlap
from .trajectory import read_tum

log = logging.getLogger(__name__)


def _open(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SequenceError(f"cannot open video {path} (not a video OpenCV can decode?)")
    return cap


def video_timestamps(path: Path, fps_fallback: float) -> tuple[np.ndarray, str]:
    """One timestamp (s) per decodable frame, and where they came from."""
    cap = _open(path)
    try:
        ms: list[float] = []
        while cap.grab():
            ms.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
        container_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
    n = len(ms)
    if n == 0:
        raise SequenceError(f"video {path} has no frames OpenCV can decode")
    t = np.asarray(ms) * 1e-3
    if n == 1 or (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
        return t - t[0], "container timestamps"
    if np.isfinite(container_fps) and container_fps > 0:
        return np.arange(n) / container_fps, f"container frame rate ({container_fps:g} fps)"
    return np.arange(n) / fps_fallback, f"fps={fps_fallback:g} from the config"


class VideoFrameSource:
    """Frame i decoded on demand; reading an earlier frame than the last one reopens the file."""

    def __init__(self, path: Path, n_frames: int):
        self.path = path
        self.n = n_frames
        self._cap: cv2.VideoCapture | None = None
        self._next = 0
        self.restarts = 0

    def read(self, i: int) -> np.ndarray:
        if self._cap is None or i < self._next:
            self.close()
            self._cap = _open(self.path)
            self._next = 0
            self.restarts += 1
        while self._next < i:  # skip without decoding to colour
            if not self._cap.grab():
                raise FrameError(f"frame {i}: the video ended early")
            self._next += 1
        ok, img = self._cap.read()
        self._next += 1
        if not ok or img is None:
            raise FrameError(f"frame {i}: cannot decode this video frame")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        return img

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap = None


def beside(video: Path, name: str) -> Path | None:
    """``<stem>.<name>`` beside the video, else ``<name>`` in its folder, else None."""
    for p in (video.with_name(f"{video.stem}.{name}"), video.with_name(name)):
        if p.is_file():
            return p
    return None


def load_video(path: Path, cam_cfg: CameraConfig | None, fps: float) -> StreamedSequence:
    path = Path(path)
    if not path.is_file():
        raise SequenceError(f"video file not found: {path}")
    warnings: list[str] = []
    camera = camera_from_config(cam_cfg, "video", warnings)
    times, how = video_timestamps(path, fps)
    if how != "container timestamps":
        warnings.append(f"video timestamps from the {how}")
    source = VideoFrameSource(path, len(times))
    first = source.read(0)
    if first.shape != (camera.height, camera.width):
        source.close()
        raise SequenceError(f"the config's camera section says {camera.width}x{camera.height} but the video is "
                            f"{first.shape[1]}x{first.shape[0]}")
    odometry = None
    odo_path = beside(path, "odometry.csv")
    if odo_path is not None:
        odometry = read_odometry_csv(odo_path)
        warnings.extend(check_odometry_overlap(odometry, times))
    groundtruth = None
    gt_path = beside(path, "groundtruth.txt")
    if gt_path is not None:
        gt = read_tum(gt_path)
        T, inside = interp_poses(gt.timestamps, gt.T_world_base, times)
        if inside.sum() >= 2:
            groundtruth = anchor(times[inside], T[inside])
        else:
            warnings.append(f"{gt_path.name} does not cover the video's time span: not used")
    log.info("video %s: %d frames, timestamps from the %s", path.name, len(times), how)
    return StreamedSequence(path, [], times, camera, odometry, groundtruth, warnings, name=path.stem, source=source)


def load(cfg: Config) -> StreamedSequence:
    """The loader's entry in the dataset registry (``windowvo.io.load``)."""
    return load_video(cfg.sequence, cfg.camera, cfg.fps)
