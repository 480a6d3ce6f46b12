"""``python -m windowvo.convert CONFIG OUT``: write any supported dataset in the native layout.

The config names the input (``sequence:`` and ``dataset: kitti | tum | euroc | folder | rosbag |
video``, plus ``camera:`` where the layout lacks intrinsics, ``rosbag:`` for a bag's topics, and
``odometry_synthesis:`` to add labelled synthetic wheel odometry); ``output`` may be omitted.
Image files are copied as they are; frames of a bag or a video are written as PNG. Everything is
written into a temporary folder beside OUT, renamed to OUT at the end: a convert that fails leaves
no half-written OUT (and OUT, when it exists, must be an empty folder).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import cv2

from ..errors import FrameError, WindowVOError
from ..io.odometry import write_odometry_csv
from ..io.sequence import StreamedSequence, write_camera_yaml
from ..io.trajectory import write_tum


def check_output_folder(out: Path | str) -> Path:
    """OUT as a path, when it is free to convert into (missing, or an empty folder); else a ``WindowVOError``."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise WindowVOError(f"output {out} exists and is not an empty folder: choose another or remove it")
    return out


def convert(seq, out: Path | str) -> None:
    """Write ``seq`` in the native layout to ``out`` (missing or empty), through a temporary folder beside it
    that is renamed to ``out`` at the end and removed when anything fails."""
    out = check_output_folder(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        write_native(seq, tmp)
        if out.is_dir():
            out.rmdir()  # empty (checked above)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_native(seq, out: Path) -> None:
    """The files of the native layout for ``seq`` in the existing folder ``out``."""
    (out / "images").mkdir(parents=True, exist_ok=True)
    width = max(6, len(str(len(seq))))
    times = seq.timestamps
    if isinstance(seq, StreamedSequence):
        # Frames inside a container (bag, video): decode one at a time and write PNGs (lossless).
        # A frame that cannot be decoded is left out, with its timestamp.
        kept: list[int] = []
        for i in range(len(seq)):
            try:
                img = seq.read_image(i)
            except FrameError as err:
                print(f"windowvo.convert: warning: {err}; left out", file=sys.stderr)
                continue
            cv2.imwrite(str(out / "images" / f"{len(kept):0{width}d}.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            kept.append(i)
        seq.close()
        times = seq.timestamps[kept]
    else:
        for i, p in enumerate(seq.image_paths):
            shutil.copyfile(p, out / "images" / f"{i:0{width}d}{p.suffix.lower()}")
    (out / "times.txt").write_text("".join(f"{t:.9f}\n" for t in times))
    write_camera_yaml(out / "camera.yaml", seq.camera)
    if seq.odometry is not None:
        write_odometry_csv(out / "odometry.csv", seq.odometry)
    if seq.groundtruth is not None:
        write_tum(out / "groundtruth.txt", seq.groundtruth.timestamps, seq.groundtruth.T_world_base,
                  header=f"ground truth of {seq.name}: T_world_base (TUM), world = base at the first frame")
