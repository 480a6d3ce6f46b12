"""``python -m windowvo.convert CONFIG OUT``: write any supported dataset in the native layout.

The config names the input (``sequence:`` and ``dataset: kitti | tum | euroc | folder | rosbag |
video``, plus ``camera:`` where the layout lacks intrinsics, ``rosbag:`` for a bag's topics, and
``odometry_synthesis:`` to add labelled synthetic wheel odometry); ``output`` may be omitted.
Image files are copied as they are; frames of a bag or a video are written as PNG.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2
import yaml

from . import io
from .config import apply_overrides, config_from_dict
from .errors import FrameError, WindowVOError, cli_error
from .io.odometry import write_odometry_csv
from .io.sequence import StreamedSequence, write_camera_yaml
from .io.trajectory import write_tum


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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.convert", description=__doc__.splitlines()[0].strip("`"))
    p.add_argument("config", help="YAML config naming sequence and dataset")
    p.add_argument("out", help="output folder (native layout)")
    p.add_argument("overrides", nargs="*", help="dotted overrides, e.g. odometry_synthesis.enabled=true")
    a = p.parse_args(argv)
    try:
        path = Path(a.config)
        if not path.is_file():
            raise WindowVOError(f"config file not found: {path}")
        data = yaml.safe_load(path.read_text()) or {}
        if not isinstance(data, dict):
            raise WindowVOError("config must be a mapping")
        data.setdefault("output", str(a.out))
        cfg = config_from_dict(apply_overrides(data, a.overrides), base_dir=path.parent.resolve())
        seq = io.load(cfg)
        convert(seq, Path(a.out))
    except (WindowVOError, yaml.YAMLError) as err:
        return cli_error(err, "windowvo.convert")
    print(f"wrote {len(seq)} frames of {seq.name} to {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
