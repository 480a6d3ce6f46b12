"""``python -m windowvo.eval GROUNDTRUTH ESTIMATE [--plot out.png]``: accuracy of a TUM trajectory."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import WindowVOError, cli_error
from ..io.trajectory import read_tum
from .metrics import evaluate, plot_trajectories

UP_TO_SCALE_MARK = "up to scale"  # windowvo writes it into a monocular trajectory's header


def says_up_to_scale(path: Path) -> bool:
    """True when the TUM file's comment lines say the trajectory is up to scale."""
    try:
        with Path(path).open() as fh:
            for line in fh:
                s = line.strip()
                if s and not s.startswith("#"):
                    return False
                if UP_TO_SCALE_MARK in s:
                    return True
    except (OSError, UnicodeDecodeError):
        return False
    return False


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.eval", description="ATE (SE(3) and Sim(3)), RPE per metre "
                                "and end drift of an estimate against ground truth, both TUM files (T_world_base). "
                                "A monocular estimate (its header says 'up to scale', or --monocular) gets RPE and "
                                "end drift after the Sim(3) scale, and no ATE SE(3).")
    p.add_argument("groundtruth")
    p.add_argument("estimate")
    p.add_argument("--plot", help="write a top-down PNG plot here")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--max-time-diff", type=float, default=0.02, help="s, for associating poses")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--monocular", action="store_true", help="the estimate is up to scale")
    scale.add_argument("--metric", action="store_true", help="the estimate is metric, whatever its header says")
    a = p.parse_args(argv)
    try:
        gt, est = read_tum(a.groundtruth), read_tum(a.estimate)
        monocular = a.monocular or (not a.metric and says_up_to_scale(a.estimate))
        rep = evaluate(gt, est, a.max_time_diff, monocular=monocular)
        if a.plot:
            plot_trajectories(a.plot, gt, {"estimate": est})
    except WindowVOError as err:
        return cli_error(err, "windowvo.eval")
    print(json.dumps(rep.as_dict(), indent=2) if a.json else rep.summary())
    return 0


if __name__ == "__main__":
    sys.exit(main())
