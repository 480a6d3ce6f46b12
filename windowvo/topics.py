"""``python -m windowvo.topics BAG``: what a ROS bag holds and what windowvo would use from it.

Lists every topic with its type, message count and mean rate, then the topic (or /tf frames)
windowvo would use for images, camera_info, wheel odometry, the camera mounting and ground
truth, and why, or what is ambiguous or missing. ``--config`` applies a config's ``rosbag:``
and ``camera:`` sections, as a run would.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from .config import CameraConfig, RosbagConfig, apply_overrides, config_from_dict
from .errors import WindowVOError, cli_error


def type_name(msgtype: str, ros1: bool) -> str:
    """A message type in its bag's convention: ``sensor_msgs/Image`` in ROS 1, ``sensor_msgs/msg/Image`` in ROS 2."""
    parts = msgtype.split("/")
    if ros1 and len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    return msgtype


def report(bag_path: Path, rc: RosbagConfig, cam_cfg: CameraConfig | None) -> str:
    from .io.rosbag import BagReader, describe_usage, topic_stats

    bag = BagReader(bag_path)
    try:
        kind = "ROS 1 bag" if not bag.is2 else "ROS 2 bag"
        span = (bag.end_ns - bag.start_ns) * 1e-9
        lines = [f"{bag_path}: {kind}, {span:.1f} s, {sum(t.count for t in bag.topics.values())} messages", "",
                 "| topic | type | messages | rate Hz |", "|---|---|---|---|"]
        for t in topic_stats(bag):
            rate = f"{t.rate_hz:.1f}" if t.rate_hz is not None else "-"
            lines.append(f"| {t.name} | {type_name(t.msgtype, not bag.is2)} | {t.count} | {rate} |")
        lines += ["", "windowvo would use:"]
        lines += [f"  {line}" for line in describe_usage(bag, rc, cam_cfg)]
        return "\n".join(lines)
    finally:
        bag.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.topics", description=__doc__.splitlines()[0].replace("`", ""))
    p.add_argument("bag", help="ROS 1 .bag file, ROS 2 bag folder, or a .db3 / .mcap file")
    p.add_argument("--config", help="YAML config whose rosbag: and camera: sections apply")
    p.add_argument("overrides", nargs="*", help="dotted overrides, e.g. rosbag.image_topic=/cam0/image_raw")
    a = p.parse_args(argv)
    try:
        data: dict = {}
        base = Path.cwd()
        if a.config:
            path = Path(a.config)
            if not path.is_file():
                raise WindowVOError(f"config file not found: {path}")
            try:
                data = yaml.safe_load(path.read_text()) or {}
            except yaml.YAMLError:
                raise WindowVOError(f"config {path} is not valid YAML") from None
            if not isinstance(data, dict):
                raise WindowVOError(f"invalid config {path}: the top level must be a mapping")
            base = path.parent.resolve()
        data = apply_overrides(data, a.overrides)
        data.setdefault("sequence", str(a.bag))
        data.setdefault("output", ".")
        data["dataset"] = "rosbag"
        cfg = config_from_dict(data, base_dir=base)
        print(report(Path(a.bag), cfg.rosbag, cfg.camera))
    except WindowVOError as err:
        return cli_error(err)
    return 0


if __name__ == "__main__":
    sys.exit(main())
