"""``python -m windowvo.eval GROUNDTRUTH ESTIMATE [--plot out.png]``: accuracy of a TUM trajectory."""

from __future__ import annotations

import argparse
import json
import sys

from ..errors import WindowVOError
from ..io.trajectory import read_tum
from .metrics import evaluate, plot_trajectories


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.eval", description="ATE (SE(3) and Sim(3)), RPE per metre "
                                "and end drift of an estimate against ground truth, both TUM files (T_world_base).")
    p.add_argument("groundtruth")
    p.add_argument("estimate")
    p.add_argument("--plot", help="write a top-down PNG plot here")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--max-time-diff", type=float, default=0.02, help="s, for associating poses")
    a = p.parse_args(argv)
    try:
        gt, est = read_tum(a.groundtruth), read_tum(a.estimate)
        rep = evaluate(gt, est, a.max_time_diff)
        if a.plot:
            plot_trajectories(a.plot, gt, {"estimate": est})
    except WindowVOError as err:
        print(f"windowvo.eval: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(rep.as_dict(), indent=2) if a.json else rep.summary())
    return 0


if __name__ == "__main__":
    sys.exit(main())
