"""``python -m windowvo.convert CONFIG OUT``: write any supported dataset in the native layout.

The config names the input (``sequence:`` and ``dataset: kitti | tum | euroc | folder | rosbag |
video``, plus ``camera:`` where the layout lacks intrinsics, ``rosbag:`` for a bag's topics, and
``odometry_synthesis:`` to add labelled synthetic wheel odometry); ``output`` may be omitted.
Image files are copied as they are; frames of a bag or a video are written as PNG.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2

from ..errors import FrameError
from ..io.odometry import write_odometry_csv
from ..io.sequence import StreamedSequence, write_camera_yaml
from ..io.trajectory import write_tum


def convert(seq, out: Path) -> None:
    out = Path(out)
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
