"""Command line: ``python -m windowvo.scale_compare BEFORE AFTER`` (see :mod:`windowvo.tools.scale_compare`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import WindowVOError, cli_error
from ..tools.scale_compare import compare, comparison_text

PROG = "python -m windowvo.scale_compare"


def load_results(where: str) -> dict:
    """A scale suite's results: a ``scale_suite.json``, or the folder holding it (or ``scale/scale_suite.json``, the
    benchmark's ``--out``)."""
    p = Path(where)
    for candidate in (p, p / "scale_suite.json", p / "scale" / "scale_suite.json"):
        if candidate.is_file():
            try:
                data = json.loads(candidate.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
                raise WindowVOError(f"cannot read {candidate}: {err}") from None
            if not isinstance(data, dict) or not isinstance(data.get("rows"), list):
                raise WindowVOError(f"{candidate} is not a scale suite's results (no rows)")
            return data
    raise WindowVOError(f"no scale suite results at {p} (python -m windowvo.bench --suite scale --out DIR writes "
                        "DIR/scale/scale_suite.json)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description="Compare two scale-suite results (python -m windowvo.bench "
                                "--suite scale): per way (fused, floor only) the geometric mean and the worst of the "
                                "ATE ratios after / before, per scene, against the old seeds' spread, and the suite's "
                                "summary side by side.")
    p.add_argument("before", help="the results before the change: a --out folder of the benchmark or its "
                   "scale_suite.json")
    p.add_argument("after", help="the results after it")
    a = p.parse_args(argv)
    try:
        before, after = load_results(a.before), load_results(a.after)
        result = compare(before, after)
        if not result.sequences:
            raise WindowVOError(f"{a.before} and {a.after} hold no sequence in common")
        text = comparison_text(result)
    except WindowVOError as err:
        return cli_error(err, PROG)
    except OSError as err:
        return cli_error(f"cannot read the results: {err}", PROG)
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError, RecursionError) as err:
        return cli_error(f"malformed scale suite results: {type(err).__name__} {err}", PROG)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
