"""The native sequence folder: the contract every dataset converts to.

::

    images/          frames (png/jpg/bmp), in file-name order
    times.txt        one timestamp (s) per frame; optional, else ``fps`` from the config
    camera.yaml      width, height, fx, fy, cx, cy, distortion_model, distortion, T_base_cam
    odometry.csv     optional wheel odometry (timestamp,x,y,yaw), same clock as times.txt
    groundtruth.txt  optional, TUM format: pose of the base in world
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
import yaml

from ..camera import CameraModel, DistortionModel
from ..config import DatasetKind
from ..errors import CalibrationError, FrameError, SequenceError
from ..yamlio import dump_yaml, safe_load_yaml
from .odometry import WheelOdometry, read_odometry_csv
from .trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".tif", ".tiff"}
CAMERA_KEYS = {"width", "height", "fx", "fy", "cx", "cy", "distortion_model", "distortion", "T_base_cam"}


@dataclass
class Sequence:
    root: Path
    image_paths: list[Path]
    timestamps: np.ndarray
    camera: CameraModel
    odometry: WheelOdometry | None = None
    groundtruth: Trajectory | None = None
    warnings: list[str] = field(default_factory=list)
    name: str = ""
    first_frame: int = 0  # index, in the sequence it was cut from, of this one's frame 0 (see subsequence)

    def __len__(self) -> int:
        return len(self.image_paths)

    def frame_name(self, i: int) -> str:
        """File name of frame i (per-frame masks in ``frontend.mask_folder`` use the same name)."""
        return self.image_paths[i].name

    def read_image(self, i: int) -> np.ndarray:
        """Grayscale uint8 image of frame i; raises FrameError when it cannot be used (the message names the
        frame by its index in the whole sequence)."""
        p = self.image_paths[i]
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FrameError(f"frame {self.first_frame + i} ({p.name}): unreadable image file")
        if img.shape != (self.camera.height, self.camera.width):
            raise FrameError(
                f"frame {self.first_frame + i} ({p.name}): size {img.shape[1]}x{img.shape[0]} differs from camera "
                f"{self.camera.width}x{self.camera.height}"
            )
        return img


class FrameSource(Protocol):
    """Frames decoded on demand from a container (a ROS bag, a video file).

    Reads are cheapest in increasing index order (a forward iterator); an earlier index
    restarts the underlying reader.
    """

    def read(self, i: int) -> np.ndarray:
        """Grayscale uint8 image of frame i; raises FrameError when that frame cannot be decoded."""
        ...

    def close(self) -> None: ...


@dataclass
class StreamedSequence(Sequence):
    """A sequence whose frames live in one container file, decoded on demand (``image_paths`` is empty).

    Only the timestamps are held in memory, so memory stays flat for any length.
    """

    source: FrameSource | None = None

    def __len__(self) -> int:
        return len(self.timestamps)

    def frame_name(self, i: int) -> str:
        return f"{self.first_frame + i:06d}.png"

    def read_image(self, i: int) -> np.ndarray:
        if self.source is None:
            raise FrameError(f"frame {i}: the sequence has no frame source")
        img = self.source.read(self.first_frame + i)
        if img.shape != (self.camera.height, self.camera.width):
            raise FrameError(
                f"frame {self.first_frame + i}: size {img.shape[1]}x{img.shape[0]} differs from camera "
                f"{self.camera.width}x{self.camera.height}"
            )
        return img

    def close(self) -> None:
        if self.source is not None:
            self.source.close()


def subsequence(seq: Sequence, first: int, end: int | None = None) -> Sequence:
    """Frames ``first .. end - 1`` of ``seq`` as a sequence of their own (``end``: None for the last frame).

    Its frame ``i`` is frame ``first + i`` of ``seq`` (``first_frame`` says where it starts, so a run of it can
    name its frames by their index in the whole sequence); its wheel odometry starts at the last sample at or
    before frame ``first``'s time (the wheel pose at that frame is interpolated, not extrapolated); the ground
    truth is the whole sequence's. A streamed sequence shares its frame source."""
    end = len(seq) if end is None else min(end, len(seq))
    if not 0 <= first < end:
        raise SequenceError(f"no frame {first} in {seq.root} ({len(seq)} frames, up to frame {end - 1} used)")
    odo = seq.odometry
    if odo is not None:
        ts = odo.timestamps
        i0 = max(int(np.searchsorted(ts, seq.timestamps[first], side="right")) - 1, 0)
        odo = dataclasses.replace(odo, timestamps=ts[i0:], x=odo.x[i0:], y=odo.y[i0:], yaw=odo.yaw[i0:],
                                  rejected_times=odo.rejected_times[odo.rejected_times >= ts[i0]])
    return dataclasses.replace(seq, image_paths=seq.image_paths[first:end], timestamps=seq.timestamps[first:end],
                               odometry=odo, warnings=list(seq.warnings), first_frame=seq.first_frame + first)


BAG_SUFFIXES = (".bag", ".db3", ".mcap")
VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov", ".webm", ".m4v", ".mpg", ".mpeg")


def _first_with_suffix(folder: Path, suffixes: tuple[str, ...]) -> Path | None:
    try:
        return next((p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() in suffixes), None)
    except OSError:
        return None


def guess_layout(path: Path | str) -> tuple[DatasetKind, str] | None:
    """The dataset kind another layout's folder (or file) looks like, with what it looks like, or None.

    kitti: ``image_0/`` and ``calib.txt``; tum: ``rgb.txt``; euroc: ``mav0/``; rosbag: a ``.bag``, ``.db3``
    or ``.mcap`` file (or a folder with one, or a ROS 2 ``metadata.yaml``); video: a video file (or a folder
    with one); folder: images directly in the folder."""
    path = Path(path)
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix in BAG_SUFFIXES:
            return DatasetKind.ROSBAG, "a ROS bag"
        return (DatasetKind.VIDEO, "a video file") if suffix in VIDEO_SUFFIXES else None
    if not path.is_dir():
        return None
    if (path / "image_0").is_dir() and (path / "calib.txt").is_file():
        return DatasetKind.KITTI, "a KITTI folder"
    if (path / "rgb.txt").is_file():
        return DatasetKind.TUM, "a TUM RGB-D folder"
    if (path / "mav0").is_dir():
        return DatasetKind.EUROC, "a EuRoC folder"
    if (path / "metadata.yaml").is_file() or _first_with_suffix(path, BAG_SUFFIXES) is not None:
        return DatasetKind.ROSBAG, "a ROS bag"
    video = _first_with_suffix(path, VIDEO_SUFFIXES)
    if video is not None:
        return DatasetKind.VIDEO, f"a folder with a video ({video.name}; point sequence at the file)"
    if _first_with_suffix(path, tuple(IMAGE_SUFFIXES)) is not None:
        return DatasetKind.FOLDER, "a folder of images (no images/ subfolder)"
    return None


def layout_hint(path: Path | str) -> str:
    """``: ... looks like a KITTI folder: set dataset: kitti`` for a sequence of another layout, else ``""``."""
    guess = guess_layout(path)
    if guess is None:
        return ""
    kind, what = guess
    return f"; {Path(path).name} looks like {what}: set dataset: {kind.value}"


def list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise SequenceError(f"image folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise SequenceError(f"no images (png/jpg/bmp) in {folder}")
    return files


def read_times(path: Path, n_frames: int) -> np.ndarray:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise SequenceError(f"cannot read {path.name}: {err}") from None
    vals = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            vals.append(float(s.split()[0].rstrip(",")))
        except ValueError:
            raise SequenceError(f"{path.name}:{lineno}: not a timestamp: '{s}'") from None
    t = np.asarray(vals, dtype=float)
    if len(t) != n_frames:
        raise SequenceError(f"{path.name} has {len(t)} timestamps but images/ has {n_frames} frames")
    if not np.all(np.isfinite(t)):
        raise SequenceError(f"{path.name}: contains non-finite timestamps")
    if np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0))
        raise SequenceError(f"{path.name}: timestamps are not strictly increasing (line {i + 2})")
    return t


def _number(d: dict, key: str, path: Path) -> float:
    if key not in d:
        raise CalibrationError(f"{path.name}: missing key '{key}'")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CalibrationError(f"{path.name}: '{key}' must be a number, got {v!r}")
    if not np.isfinite(v):
        raise CalibrationError(f"{path.name}: '{key}' must be finite")
    return float(v)


def read_camera_yaml(path: Path | str) -> CameraModel:
    """The camera of a ``camera.yaml`` (width, height, fx, fy, cx, cy, distortion_model, distortion, T_base_cam)."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"camera calibration not found: {path}")
    try:
        d = safe_load_yaml(path.read_text())
    except (OSError, UnicodeDecodeError) as err:
        raise CalibrationError(f"cannot read {path.name}: {err}") from None
    except yaml.YAMLError:
        raise CalibrationError(f"{path.name} is not valid YAML") from None
    if not isinstance(d, dict):
        raise CalibrationError(f"{path.name}: expected a mapping with width, height, fx, fy, cx, cy")
    unknown = set(d) - CAMERA_KEYS
    if unknown:
        raise CalibrationError(f"{path.name}: unknown key '{sorted(unknown, key=str)[0]}'")  # keys of any YAML type
    w, h = _number(d, "width", path), _number(d, "height", path)
    if w != int(w) or h != int(h):
        raise CalibrationError(f"{path.name}: width and height must be whole numbers")
    model = d.get("distortion_model", "none")
    try:
        model = DistortionModel(str(model).lower())
    except ValueError:
        raise CalibrationError(
            f"{path.name}: distortion_model must be none, radtan or equidistant, got {model!r}"
        ) from None
    dist = d.get("distortion", []) or []
    if not isinstance(dist, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in dist):
        raise CalibrationError(f"{path.name}: 'distortion' must be a list of numbers")
    T = d.get("T_base_cam")
    if T is None:
        raise CalibrationError(f"{path.name}: missing key 'T_base_cam' (16 numbers, row major)")
    if isinstance(T, list) and len(T) == 4 and all(isinstance(r, list) for r in T):
        T = [x for r in T for x in r]
    if not isinstance(T, list) or len(T) != 16 or not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in T
    ):
        raise CalibrationError(f"{path.name}: 'T_base_cam' must be 16 numbers, row major")
    return CameraModel(
        width=int(w),
        height=int(h),
        fx=_number(d, "fx", path),
        fy=_number(d, "fy", path),
        cx=_number(d, "cx", path),
        cy=_number(d, "cy", path),
        distortion_model=model,
        distortion=tuple(float(x) for x in dist),
        T_base_cam=np.asarray(T, dtype=float).reshape(4, 4),
    )


def write_camera_yaml(path: Path | str, cam: CameraModel) -> None:
    """Write ``cam`` as a ``camera.yaml`` (plain numbers: :func:`read_camera_yaml` reads it back)."""
    Path(path).write_text(dump_yaml(cam.to_dict(), default_flow_style=None))


def load_native(root: Path | str, fps: float = 20.0) -> Sequence:
    root = Path(root)
    if not root.is_dir():
        hint = layout_hint(root) if root.exists() else ""
        raise SequenceError(f"sequence folder not found: {root}{hint}")
    if not (root / "images").is_dir():
        raise SequenceError(f"image folder not found: {root / 'images'}{layout_hint(root)}")
    images = list_images(root / "images")
    camera = read_camera_yaml(root / "camera.yaml")
    warnings: list[str] = []
    times_path = root / "times.txt"
    if times_path.is_file():
        timestamps = read_times(times_path, len(images))
    else:
        timestamps = np.arange(len(images), dtype=float) / fps
        warnings.append(f"no times.txt: timestamps from fps={fps}")
    # Check the first image's size here: a calibration for another camera is a sequence error.
    first = cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE)
    if first is not None and first.shape != (camera.height, camera.width):
        raise CalibrationError(
            f"camera.yaml says {camera.width}x{camera.height} but {images[0].name} is {first.shape[1]}x{first.shape[0]}"
        )
    require_two_frames(len(timestamps), root / "images")
    odometry = None
    odo_path = root / "odometry.csv"
    if odo_path.is_file():
        odometry = read_odometry_csv(odo_path)
        warnings.extend(check_odometry_overlap(odometry, timestamps))
    groundtruth = None
    gt_path = root / "groundtruth.txt"
    if gt_path.is_file():
        try:
            groundtruth = read_tum(gt_path)
        except SequenceError as err:
            # Ground truth only feeds the evaluation: a broken file must not stop the run.
            warnings.append(f"ground truth ignored, no evaluation: {err}")
    return Sequence(root, images, timestamps, camera, odometry, groundtruth, warnings, name=root.name)


def require_two_frames(n_frames: int, where: Path | str) -> None:
    """Odometry needs motion between frames: one frame (or none) is a clear error, before anything else."""
    if n_frames < 2:
        raise SequenceError(f"{'one frame only' if n_frames == 1 else 'no frame'}: need at least 2 (in {where})")


def check_odometry_overlap(odo: WheelOdometry, timestamps: np.ndarray) -> list[str]:
    t0, t1 = float(timestamps[0]), float(timestamps[-1])
    o0, o1 = float(odo.timestamps[0]), float(odo.timestamps[-1])
    overlap = min(t1, o1) - max(t0, o0)
    if overlap <= 0:
        raise SequenceError(
            f"odometry.csv covers [{o0:.3f}, {o1:.3f}] s, which does not overlap the images' [{t0:.3f}, {t1:.3f}] s"
        )
    span = max(t1 - t0, 1e-9)
    if overlap < span - 1e-6:
        return [f"odometry covers only {100.0 * overlap / span:.0f}% of the images' time span"]
    return []
