"""Run many independent jobs, each in its own fresh Python process, locally or on a Ray cluster.

A :class:`Task` is one command line (``python -m windowvo.run CONFIG ...``) or one picklable
Python call (:func:`call_task`, run as ``python -m windowvo.tools.executors``). :func:`run_task` runs it
as a subprocess with an optional time-out and turns every way it can end into a
:class:`TaskOutcome`: a crash in a native library (a signal), a ``windowvo: error:`` line, an
exception, a time-out. One bad job never takes the others down, and a new interpreter per job
means no state leaks between jobs (the same as ``max_tasks_per_child=1``, which Python 3.10's
``ProcessPoolExecutor`` lacks).

Executors decide where :func:`run_task` runs:

* :class:`LocalExecutor`: ``jobs`` subprocesses at a time on this machine.
* :class:`RayExecutor`: one Ray task (1 CPU) per job on a Ray cluster (``address``) or on a local
  Ray instance. The job's files must be on storage every node sees; only the small outcome
  (status, reason, the job's summary) travels through Ray's object store.
"""

from __future__ import annotations

import contextlib
import enum
import io
import json
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from ..errors import WindowVOError

ERROR_PREFIX = "windowvo: error:"
PARENT_PID_ENV = "WINDOWVO_PARENT_PID"
# ``python -c _BOOT MODULE ARGS`` is ``python -m MODULE ARGS`` that also dies (SIGTERM: it writes what it
# has) when the process that started it dies, e.g. a Ray worker killed by ray.shutdown() (Linux prctl).
_BOOT = (
    "import ctypes, os, runpy, signal, sys\n"
    "try:\n"
    "    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))\n"  # 1 = PR_SET_PDEATHSIG
    "except (OSError, AttributeError):\n"
    "    pass\n"
    f"if os.getppid() != int(os.environ.get('{PARENT_PID_ENV}', os.getppid())):\n"
    "    sys.exit(143)\n"  # the parent died before prctl took effect
    "sys.argv = sys.argv[1:]\n"
    "runpy.run_module(sys.argv[0], run_name='__main__', alter_sys=True)\n"
)
_live: set[subprocess.Popen] = set()  # task subprocesses running in this process
_live_lock = threading.Lock()
TERM_GRACE_S = 10.0  # after a time-out: SIGTERM (the run writes what it has), then SIGKILL


class ExecutorUnavailableError(WindowVOError):
    """The requested executor cannot run here (e.g. Ray is not installed or not reachable)."""


class ExecutorKind(str, enum.Enum):
    LOCAL = "local"
    RAY = "ray"


class TaskStatus(str, enum.Enum):
    OK = "ok"
    FAILED = "failed"


@dataclass(frozen=True)
class Task:
    """One job: ``python ARGS...`` in a fresh interpreter.

    ``result_json``: a JSON file the job writes on success (read back into the outcome).
    ``call``: a pickled ``(function, args, kwargs)`` fed to ``python -m windowvo.tools.executors`` on stdin
    (see :func:`call_task`); its return value comes back in the outcome.
    ``log_path``: where the job's stderr is kept (beside its outputs).
    """

    key: str
    args: tuple[str, ...] = ()
    timeout_s: float | None = None
    result_json: str | None = None
    call: bytes | None = None
    log_path: str | None = None
    env: dict[str, str] = field(default_factory=dict)


@dataclass
class TaskOutcome:
    key: str
    status: TaskStatus
    reason: str = ""
    wall_s: float = 0.0
    returncode: int | None = None
    value: Any = None  # the parsed result_json, or the call's return value

    @property
    def ok(self) -> bool:
        return self.status is TaskStatus.OK


def call_task(key: str, fn: Callable[..., Any], *args: Any, timeout_s: float | None = None,
              log_path: str | None = None, **kwargs: Any) -> Task:
    """A task that runs ``fn(*args, **kwargs)`` in a fresh interpreter (``fn`` must be importable).

    Objects defined in a module run as ``python -m package.module`` pickle as ``__main__.X``; the
    worker maps ``__main__`` back to that module (its ``__main__`` is this module instead).
    """
    main_spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    payload = {"main_module": main_spec.name if main_spec is not None else None,
               "call": pickle.dumps((fn, args, kwargs))}
    return Task(key=key, timeout_s=timeout_s, call=pickle.dumps(payload), log_path=log_path)


class _MainMappingUnpickler(pickle.Unpickler):
    def __init__(self, data: bytes, main_module: str | None):
        super().__init__(io.BytesIO(data))
        self.main_module = main_module

    def find_class(self, module: str, name: str) -> Any:
        if module == "__main__" and self.main_module:
            module = self.main_module
        return super().find_class(module, name)


def _signal_name(num: int) -> str:
    try:
        return signal.Signals(num).name
    except ValueError:
        return f"signal {num}"


def failure_reason(returncode: int, stderr: str) -> str:
    """One line saying why a job ended badly, from its exit code and its stderr."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if ln.startswith(ERROR_PREFIX):
            return ln[len(ERROR_PREFIX):].strip()
    if returncode < 0:
        return f"killed by {_signal_name(-returncode)}"
    if returncode == 130:
        return "interrupted (exit code 130)"
    if returncode == 143:
        return "stopped by SIGTERM (exit code 143)"
    last = lines[-1] if lines else "no error output"
    return f"exit code {returncode}: {last}"


def _terminate(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError):
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(TERM_GRACE_S)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        proc.wait()


def terminate_running() -> int:
    """SIGTERM every task subprocess this process is running (they write what they have); returns how many."""
    with _live_lock:
        procs = list(_live)
    for proc in procs:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
    return len(procs)


def run_task(task: Task) -> TaskOutcome:
    """Run one task in a subprocess and report how it ended (never raises for a failing job)."""
    t0 = time.perf_counter()
    env = dict(os.environ)
    env.update(task.env)
    env.setdefault("PYTHONUNBUFFERED", "1")
    env[PARENT_PID_ENV] = str(os.getpid())
    with contextlib.ExitStack() as stack:
        result_path: Path | None = Path(task.result_json) if task.result_json else None
        args = list(task.args)
        if task.call is not None:
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="windowvo_task_")))
            result_path = tmp / "result.pickle"
            args = ["-m", "windowvo.tools.executors", str(result_path)]
        if len(args) >= 2 and args[0] == "-m":
            args = ["-c", _BOOT, *args[1:]]
        if task.log_path:
            Path(task.log_path).parent.mkdir(parents=True, exist_ok=True)
            err_fh = stack.enter_context(open(task.log_path, "w+"))
        else:
            err_fh = stack.enter_context(tempfile.TemporaryFile("w+"))
        try:
            proc = subprocess.Popen([sys.executable, *args], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                    stderr=err_fh, env=env)
        except OSError as err:
            return TaskOutcome(task.key, TaskStatus.FAILED, f"cannot start: {err}", time.perf_counter() - t0)
        with _live_lock:
            _live.add(proc)
        timed_out = False
        try:
            proc.communicate(input=task.call, timeout=task.timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            _terminate(proc)
        except BaseException:
            _terminate(proc)
            raise
        finally:
            with _live_lock:
                _live.discard(proc)
        wall = time.perf_counter() - t0
        err_fh.seek(0)
        stderr = err_fh.read()
        rc = proc.returncode
        if timed_out:
            return TaskOutcome(task.key, TaskStatus.FAILED, f"timed out after {task.timeout_s:g} s", wall, rc)
        if rc != 0:
            return TaskOutcome(task.key, TaskStatus.FAILED, failure_reason(rc, stderr), wall, rc)
        value = None
        if result_path is not None:
            try:
                if task.call is not None:
                    value = pickle.loads(result_path.read_bytes())
                else:
                    value = json.loads(result_path.read_text())
            except (OSError, ValueError, pickle.UnpicklingError) as err:
                return TaskOutcome(task.key, TaskStatus.FAILED, f"no readable result {result_path.name}: {err}",
                                   wall, rc)
        return TaskOutcome(task.key, TaskStatus.OK, "", wall, rc, value)


class Executor(Protocol):
    def run(self, tasks: Iterable[Task]) -> Iterator[TaskOutcome]:
        """Run every task; yield outcomes as they finish (any order)."""
        ...


class LocalExecutor:
    """``jobs`` task subprocesses at a time on this machine (threads only wait on them)."""

    def __init__(self, jobs: int = 1):
        if jobs < 1:
            raise ExecutorUnavailableError(f"--jobs must be at least 1, got {jobs}")
        self.jobs = jobs

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskOutcome]:
        todo = list(tasks)
        with ThreadPoolExecutor(max_workers=self.jobs) as pool:
            pending: set[Future[TaskOutcome]] = {pool.submit(run_task, t) for t in todo}
            try:
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        yield fut.result()
            finally:
                if pending:  # interrupted (Ctrl-C, SIGTERM, the consumer stopped): stop the runs in flight
                    for fut in pending:
                        fut.cancel()
                    terminate_running()


RAY_OBJECT_STORE_BYTES = 100 * 1024**2  # outcomes are small; keep the shared-memory store small
RAY_MAX_RETRIES = 1  # a task whose Ray worker or node died runs once more
RAY_POLL_S = 0.5


class RayExecutor:
    """One Ray task per job, on the cluster at ``address`` or on a local Ray instance of ``jobs`` CPUs."""

    def __init__(self, jobs: int = 1, address: str | None = None):
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ExecutorUnavailableError(
                'the ray executor needs Ray: pip install "windowvo[cluster]"') from None
        if jobs < 1:
            raise ExecutorUnavailableError(f"--jobs must be at least 1, got {jobs}")
        self.jobs = jobs
        self.address = address

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskOutcome]:
        import ray

        todo = list(tasks)
        in_main = threading.current_thread() is threading.main_thread()
        term_handler = signal.getsignal(signal.SIGTERM) if in_main else None
        try:
            if self.address:
                ray.init(address=self.address, log_to_driver=False)
            else:
                ray.init(num_cpus=self.jobs, include_dashboard=False, object_store_memory=RAY_OBJECT_STORE_BYTES,
                         log_to_driver=False)
        except Exception as err:  # ConnectionError, RuntimeError, ValueError depending on the failure
            with contextlib.suppress(Exception):
                ray.shutdown()
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ExecutorUnavailableError(f"cannot start Ray ({self.address or 'local'}): {first}") from None
        if callable(term_handler):  # ray.init replaces a Python SIGTERM handler (e.g. the batch's clean stop)
            signal.signal(signal.SIGTERM, term_handler)
        try:
            # run_task never raises for a failing job, so a retry only happens when a Ray worker or node dies.
            remote = ray.remote(num_cpus=1, max_retries=RAY_MAX_RETRIES)(run_task)
            refs = {remote.remote(t): t for t in todo}
            pending = list(refs)
            while pending:
                # Collect everything finished within a short wait (cheap with thousands of tasks in flight).
                done, pending = ray.wait(pending, num_returns=len(pending), timeout=RAY_POLL_S)
                for ref in done:
                    try:
                        yield ray.get(ref)
                    except Exception as err:  # the Ray worker itself died or the task was lost
                        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
                        yield TaskOutcome(refs[ref].key, TaskStatus.FAILED, f"ray: {type(err).__name__}: {first}")
        finally:
            ray.shutdown()


def make_executor(kind: ExecutorKind, jobs: int = 1, address: str | None = None) -> Executor:
    if kind is ExecutorKind.RAY:
        return RayExecutor(jobs, address)
    if address:
        raise ExecutorUnavailableError("--address only applies to --executor ray")
    return LocalExecutor(jobs)


def values_in_processes(calls: list[tuple[str, Callable[..., Any], tuple]], jobs: int, label: str) -> list[Any]:
    """``(key, fn, args)`` calls, each in a fresh interpreter, ``jobs`` at once; the values of those that succeed,
    in order (a failure is one line on stderr, ``label: key failed: reason``, and is dropped)."""
    tasks = [call_task(key, fn, *args) for key, fn, args in calls]
    by_key = {o.key: o for o in LocalExecutor(max(1, jobs)).run(tasks)}
    values = []
    for key, _, _ in calls:
        o = by_key[key]
        if o.ok:
            values.append(o.value)
        else:
            print(f"{label}: {key} failed: {o.reason}", file=sys.stderr)
    return values


def _call_main(result_path: str) -> int:
    """Worker side of :func:`call_task`: read the pickled call on stdin, pickle its return value.

    A stop signal (SIGTERM: the parent stopping the task, timing it out or dying; Ctrl-C) ends the whole call: the
    run in progress stops between two frames, writes what it has (``runtime/stop.py``) and the call ends there, before
    any later run or other work of the call (a call may be many runs: a scale-suite case is eight). Outside a run the
    signal unwinds the call at once. The exit code is then 128 + the signal, and no value is returned."""
    from ..runtime import stop

    stop.between_runs(stop.Phase.RAISE)
    try:
        payload = pickle.loads(sys.stdin.buffer.read())
        fn, args, kwargs = _MainMappingUnpickler(payload["call"], payload["main_module"]).load()
        value = fn(*args, **kwargs)
    except stop.Interrupted as sig:
        return stop.exit_code(sig.signum)
    except WindowVOError as err:
        print(f"{ERROR_PREFIX} {err}", file=sys.stderr)
        return 2
    signum = stop.requested()
    if signum is not None:  # the last run was cut short: its value is not the call's
        return stop.exit_code(signum)
    Path(result_path).write_bytes(pickle.dumps(value))
    return 0


if __name__ == "__main__":
    sys.exit(_call_main(sys.argv[1]))
