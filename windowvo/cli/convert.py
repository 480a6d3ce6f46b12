"""Command line: ``python -m windowvo.convert CONFIG OUT`` (see :mod:`windowvo.tools.convert`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from .. import io
from ..config import apply_overrides, config_from_dict
from ..errors import WindowVOError, cli_error
from ..tools import convert as _tools_convert
from ..tools.convert import convert


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.convert", description=_tools_convert.__doc__.splitlines()[0].strip("`"))
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
