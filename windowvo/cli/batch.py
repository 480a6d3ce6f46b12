"""Command line: ``python -m windowvo.batch SPEC.yaml`` (see :mod:`windowvo.tools.batch`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable

from ..errors import WindowVOError, cli_error
from ..tools.batch import EPILOG, BatchResult, run_batch
from ..tools.executors import ExecutorKind, TaskStatus
from ..tools.helptext import plain_help


def _default_jobs() -> int:
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m windowvo.batch",
                                description="windowvo batch evaluation: sequences x a grid of configs, "
                                "each run in its own process, locally or on Ray.",
                                epilog=plain_help(EPILOG), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("spec", help="batch spec (YAML)")
    p.add_argument("--executor", choices=[k.value for k in ExecutorKind], default=ExecutorKind.LOCAL.value)
    p.add_argument("--jobs", type=int, default=None,
                   help="runs at once (local), or CPUs of the local Ray instance (default: CPUs available)")
    p.add_argument("--address", default=None, help="Ray cluster address (with --executor ray)")
    p.add_argument("--force", action="store_true", help="rerun runs that already finished")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def summary_lines(result: BatchResult) -> Iterable[str]:
    n_ok = sum(r.status is TaskStatus.OK for r in result.rows)
    yield (f"windowvo batch: {len(result.rows)} runs: {n_ok} ok ({result.n_reused} reused), {result.n_failed} failed; "
           f"{result.n_ran} ran in {result.wall_s:.1f} s ({result.executor}, {result.jobs} jobs)")
    for r in result.rows:
        if r.status is TaskStatus.FAILED:
            yield f"  failed {r.run_id}: {r.reason}"
    yield f"results: {result.files['csv']}  report: {result.files['report']}  plot: {result.files['plot']}"


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    import signal
    import threading

    previous = None
    if threading.current_thread() is threading.main_thread():
        # SIGTERM stops like Ctrl-C: runs in flight are stopped, Ray is shut down, nothing is orphaned.
        previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        result = run_batch(args.spec, ExecutorKind(args.executor), args.jobs or _default_jobs(), args.address,
                           args.force, progress=not args.no_progress)
    except WindowVOError as err:
        return cli_error(err)
    except KeyboardInterrupt:
        print("windowvo: batch interrupted; finished runs are kept and reused by the next invocation", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    print("\n".join(summary_lines(result)))
    return 1 if result.n_failed else 0


if __name__ == "__main__":
    sys.exit(main())
