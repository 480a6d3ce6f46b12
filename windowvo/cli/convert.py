"""Command line: ``python -m windowvo.convert CONFIG OUT`` (see :mod:`windowvo.tools.convert`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .. import io
from ..config import apply_overrides, config_from_dict, read_yaml_mapping
from ..errors import WindowVOError, cli_error
from ..tools import convert as _tools_convert
from ..tools.convert import check_output_folder, convert
from ..tools.helptext import first_line, plain_help


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.convert", description=first_line(_tools_convert.__doc__),
                                epilog=plain_help("\n".join((_tools_convert.__doc__ or "").splitlines()[1:])),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("config", help="YAML config naming sequence and dataset")
    p.add_argument("out", help="output folder (native layout)")
    p.add_argument("overrides", nargs="*", help="dotted overrides, e.g. odometry_synthesis.enabled=true")
    a = p.parse_args(argv)
    try:
        path = Path(a.config)
        data = read_yaml_mapping(path, "config", not_found=f"config file not found: {path}")
        data.setdefault("output", str(a.out))
        cfg = config_from_dict(apply_overrides(data, a.overrides), base_dir=path.parent.resolve())
        check_output_folder(a.out)  # before loading: a long load must not end in this error
        seq = io.load(cfg)
        convert(seq, Path(a.out))
    except WindowVOError as err:
        return cli_error(err, "windowvo.convert")
    print(f"wrote {len(seq)} frames of {seq.name} to {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
