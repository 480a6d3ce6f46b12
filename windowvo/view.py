"""``python -m windowvo.view OUTPUT_FOLDER_OR_RRD``: open a saved run in the Rerun viewer.

Uses the viewer shipped with rerun-sdk. On a machine without a screen, use
``--web`` to serve the web viewer instead.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.view", description=__doc__.splitlines()[0].strip("`"))
    p.add_argument("path", help="a run's output folder (holding recording.rrd) or an .rrd file")
    p.add_argument("--web", action="store_true", help="serve the web viewer instead of a native window")
    a = p.parse_args(argv)
    path = Path(a.path)
    rrd = path / "recording.rrd" if path.is_dir() else path
    if not rrd.is_file():
        print(f"windowvo.view: error: no recording at {rrd} (run with viz.rerun=save)", file=sys.stderr)
        return 2
    import subprocess

    cmd = [sys.executable, "-m", "rerun", str(rrd)]
    if a.web:
        cmd.insert(3, "--web-viewer")
    return subprocess.call(cmd)


if __name__ == "__main__":
    sys.exit(main())
