"""Command line: ``python -m windowvo.view OUTPUT_FOLDER_OR_RRD`` opens a saved run in the Rerun viewer.

Uses the viewer shipped with rerun-sdk. On a machine without a screen, use
``--web`` to serve the web viewer instead.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import WindowVOError, cli_error

PROG = "windowvo.view"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.view", description="Open a saved run (its output folder or an .rrd file) in the Rerun viewer.")
    p.add_argument("path", help="a run's output folder (holding recording.rrd) or an .rrd file")
    p.add_argument("--web", action="store_true", help="serve the web viewer instead of a native window")
    a = p.parse_args(argv)
    from ..viz.viewer import open_recording

    try:
        return open_recording(Path(a.path), web=a.web)
    except WindowVOError as err:
        return cli_error(err, PROG)
    except KeyboardInterrupt:  # Ctrl-C before the viewer started
        return 130


if __name__ == "__main__":
    sys.exit(main())
