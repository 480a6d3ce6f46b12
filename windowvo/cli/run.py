"""Command line: ``python -m windowvo.run [CONFIG] [key=value ...]``.

argparse and a call into :mod:`windowvo.runtime.job`. Without CONFIG, runs the embedded default
(:mod:`windowvo.runtime.default_job`): renders a short synthetic loop (cached under
./windowvo_output/default_sequence), runs VO on it, prints the accuracy and writes the
outputs to ./windowvo_output/default.
"""

from __future__ import annotations

# Light on purpose: the stop handlers are installed before OpenCV, GTSAM or pydantic are imported, so Ctrl-C and
# SIGTERM end the run with one line and exit 130/143 from its first line on (runtime/stop.py).
import argparse
import atexit
import contextlib
import logging
import os
import signal
import sys
from pathlib import Path
from typing import NoReturn

from ..runtime import stop
from .hidden_modules import pandas_hidden

log = logging.getLogger("windowvo")


EPILOG = """\
examples:
  python -m windowvo.run                                  # embedded default (synthetic loop)
  python -m windowvo.run configs/example.yaml             # your own sequence folder
  python -m windowvo.run configs/example.yaml frontend.max_features=300 viz.rerun=off

A config needs only sequence: (a native sequence folder) and output:; relative
paths are resolved against the config file. Every other key has a default; see docs/config.md. Outputs: trajectory.txt (TUM, one line per frame), stats.csv,
config_resolved.yaml, summary.json and recording.rrd (when viz.rerun=save).
Each run holds OUT/.windowvo.lock; a folder holding an earlier run's files is refused
unless --force (they are moved to OUT/previous-<time>/); the embedded default replaces its
own previous run. --resume continues a killed run from its journal (journal.jsonl) to the
end of the sequence.
Exit codes: 0 done, 2 bad input or configuration, 130 interrupted by SIGINT, 143 by SIGTERM
(results so far still written).
"""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m windowvo.run",
        description="windowvo: sliding-window visual odometry (OpenCV front end, GTSAM fixed-lag smoother) "
        "for ground robots, with wheel odometry for metric scale.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", nargs="?", help="YAML config file; omit to run the embedded default")
    p.add_argument("overrides", nargs="*", help="dotted overrides, e.g. frontend.max_features=300")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("-q", "--quiet", action="store_true", help="only warnings and the summary")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--force", action="store_true",
                     help="run even if the output folder holds an earlier run's files (moved to OUT/previous-<time>/)")
    how.add_argument("--resume", action="store_true",
                     help="continue a killed (or interrupted) run in the output folder to the end of the sequence: it is "
                          "replayed from its first frame (deterministic, checked against its journal) and goes on: "
                          "the result is the uninterrupted run's")
    return p


def main(argv: list[str] | None = None) -> int:
    stop.install()
    try:
        with pandas_hidden():  # pyarrow's import of it under rerun: 0.3 s of start-up (cli/hidden_modules.py)
            return _main(argv)
    except stop.Interrupted as intr:
        return _interrupted(intr.signum)
    except KeyboardInterrupt:  # a signal that came before the handlers (the interpreter starting)
        return _interrupted(signal.SIGINT)
    except ImportError:
        # A stop signal during a compiled module's import (gtsam) surfaces as "ImportError: initialization
        # failed", the signal's exception wrapped by the extension's init: a stop, not an error.
        signum = stop.requested()
        if signum is None:
            raise
        return _interrupted(signum)
    finally:
        if "windowvo.runtime.parallel" in sys.modules:  # a pipelined run: leave no helper process behind
            from ..runtime.parallel import stop_resource_tracker

            stop_resource_tracker()


def exit_without_teardown(code: int) -> NoReturn:
    """End the process once ``main`` has returned, without the interpreter's teardown.

    By then every output is written and closed, the recording flushed and closed, the back-end process and
    multiprocessing's helper stopped. What is left is freeing the modules (rerun, pandas, GTSAM, evo...): about
    0.3-0.5 s of a whole run (docs/performance.md). The exit handlers still run (rerun's shutdown among them),
    and the standard streams and logging are flushed first; only the freeing is skipped. Under a profiler or a
    coverage tracer the normal exit is kept (they write their results at exit)."""
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)  # CPython's; absent elsewhere: nothing to skip
    if run_exit_handlers is None or sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(code)
    logging.shutdown()
    run_exit_handlers()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _interrupted(signum: int) -> int:
    name = signal.Signals(signum).name
    print(f"windowvo: interrupted by {name} before the first frame was processed: nothing written", file=sys.stderr)
    return stop.exit_code(signum)


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else (logging.WARNING if args.quiet else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("matplotlib").setLevel(logging.WARNING)
    from ..config import ConfigError, load_config
    from ..errors import WindowVOError, cli_error
    from ..runtime.default_job import DEFAULT_ROOT, check_output_folder, default_config, prepare_output
    from ..runtime.outfolder import OutputLock

    stop.set_phase(stop.Phase.RAISE)  # a signal during the imports above unwinds here
    config_arg = args.config
    overrides = list(args.overrides)
    if config_arg is not None and "=" in config_arg and not Path(config_arg).exists():
        overrides.insert(0, config_arg)
        config_arg = None
    try:
        cfg = load_config(config_arg, overrides) if config_arg else default_config(overrides, DEFAULT_ROOT)
        if args.no_progress:
            cfg.progress = False
        check_output_folder(cfg.output)
        with OutputLock.of(cfg.output):
            if args.resume:
                from ..runtime.resume import resume

                result = resume(cfg)  # a signal during the continuation: exit 130/143 as a run does
            else:
                prepare_output(cfg.output, force=args.force, replace=config_arg is None)
                from ..runtime.job import run_and_report  # the pipeline (GTSAM, OpenCV) is loaded only now

                result = run_and_report(cfg)
    except (ConfigError, WindowVOError) as err:
        return cli_error(err)
    signum = stop.requested()
    if signum is not None:
        return stop.exit_code(signum)
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
