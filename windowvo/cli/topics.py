"""Command line: ``python -m windowvo.topics BAG [--config CONFIG]`` (see :mod:`windowvo.tools.topics`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from ..config import apply_overrides, config_from_dict
from ..errors import WindowVOError, cli_error
from ..tools import topics as _tools_topics
from ..tools.helptext import first_line
from ..tools.topics import report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.topics", description=first_line(_tools_topics.__doc__))
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
