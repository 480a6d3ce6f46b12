"""``python -m windowvo.topics BAG``: what a ROS bag holds and what windowvo would use from it.

Lists every topic with its type, message count and mean rate, then the topic (or /tf frames)
windowvo would use for images, camera_info, wheel odometry, the camera mounting and ground
truth, and why, or what is ambiguous or missing. ``--config`` applies a config's ``rosbag:``
and ``camera:`` sections, as a run would.
"""

from __future__ import annotations

from pathlib import Path

from ..config import CameraConfig, RosbagConfig


def type_name(msgtype: str, ros1: bool) -> str:
    """A message type in its bag's convention: ``sensor_msgs/Image`` in ROS 1, ``sensor_msgs/msg/Image`` in ROS 2."""
    parts = msgtype.split("/")
    if ros1 and len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    return msgtype


def report(bag_path: Path, rc: RosbagConfig, cam_cfg: CameraConfig | None) -> str:
    from ..io.rosbag import BagReader, describe_usage, topic_stats

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
