"""One run per output folder, and never two runs' files mixed in one.

- :class:`OutputLock`: ``OUT/.windowvo.lock`` holds the running process's PID under ``fcntl.flock``; a second run
  into the folder fails with one line naming that PID. The kernel drops the lock when its process dies (even by
  SIGKILL), so a stale lock file of a dead process is simply taken over.
- :func:`previous_run_files`: the files an earlier run left in the folder; :func:`move_aside` puts them into
  ``OUT/previous-<timestamp>/`` (``--force``), :func:`remove_previous` deletes them (the embedded default job
  replaces its own previous run).
- :func:`keep_first_pass` / :func:`restore_first_pass`: a run made again with its wheel clock's offset keeps its first
  pass in ``OUT/first_pass/`` (an earlier run's files too, for the functions above), and puts it back when the second
  pass fails or is stopped.

Light on imports: the command line uses it before the pipeline is loaded.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import time
from pathlib import Path
from typing import IO

from ..errors import WindowVOError

LOCK_NAME = ".windowvo.lock"
# Everything a run writes into its output folder.
RUN_FILES = ("trajectory.txt", "trajectory_online.txt", "stats.csv", "summary.json", "config_resolved.yaml",
             "recording.rrd", "journal.jsonl")
# A run made again with its wheel clock's offset (``backend.odometry.time_offset_second_pass``): the first pass's
# files, in this folder inside the output folder.
FIRST_PASS_DIR = "first_pass"


class OutputBusyError(WindowVOError):
    """Another run holds the output folder."""


class OutputLock:
    """An exclusive lock on an output folder for this process's run (re-entrant within the process)."""

    _held: dict[Path, OutputLock] = {}

    def __init__(self, out: Path):
        self.out = Path(out).resolve()
        self._fh: IO[str] | None = None
        self._depth = 0

    @classmethod
    def of(cls, out: Path) -> OutputLock:
        key = Path(out).resolve()
        if key not in cls._held:
            cls._held[key] = cls(key)
        return cls._held[key]

    def acquire(self) -> None:
        if self._depth == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            fh = self._lock_file()
            fh.seek(0)
            fh.truncate()
            fh.write(f"{os.getpid()}\n")
            fh.flush()
            self._fh = fh
        self._depth += 1

    def _lock_file(self) -> IO[str]:
        """The lock file, flocked. A file unlinked by its releasing owner between our open and our flock is not
        the lock any more: open again."""
        path = self.out / LOCK_NAME
        while True:
            fh = path.open("a+")
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                fh.seek(0)
                pid = fh.read().strip() or "unknown"
                fh.close()
                raise OutputBusyError(f"output folder '{self.out}' is in use by another windowvo run (PID {pid}); "
                                      "wait for it to end or choose another output") from None
            try:
                same = os.stat(path).st_ino == os.fstat(fh.fileno()).st_ino
            except FileNotFoundError:
                same = False
            if same:
                return fh
            fh.close()

    def release(self) -> None:
        self._depth = max(self._depth - 1, 0)
        if self._depth == 0 and self._fh is not None:
            with contextlib.suppress(OSError):
                (self.out / LOCK_NAME).unlink()
            self._fh.close()  # closing drops the flock
            self._fh = None
            type(self)._held.pop(self.out, None)

    def __enter__(self) -> OutputLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def previous_run_files(out: Path) -> list[Path]:
    """The files of an earlier run in ``out`` (none when the folder is new or empty of them)."""
    out = Path(out)
    files = [out / name for name in RUN_FILES if (out / name).exists() or (out / name).is_symlink()]
    return files + ([out / FIRST_PASS_DIR] if (out / FIRST_PASS_DIR).is_dir() else [])


def check_writable_names(out: Path) -> None:
    """Fail before the run, not after it, when an output name is taken by something that is not a file."""
    for name in RUN_FILES:
        p = Path(out) / name
        if p.exists() and not p.is_file():
            raise WindowVOError(f"output folder '{out}' holds a directory (or other non-file) named '{name}': the "
                                "run could not write it; remove it or choose another output")


def move_aside(out: Path) -> Path | None:
    """Move an earlier run's files into ``out/previous-<timestamp>/``; returns that folder (None: nothing moved)."""
    files = previous_run_files(out)
    if not files:
        return None
    stamp = time.strftime("%Y%m%d-%H%M%S")
    dest = Path(out) / f"previous-{stamp}"
    n = 1
    while dest.exists():
        n += 1
        dest = Path(out) / f"previous-{stamp}-{n}"
    dest.mkdir()
    for f in files:
        os.replace(f, dest / f.name)
    return dest


def remove_previous(out: Path) -> int:
    """Delete an earlier run's files from ``out`` (regular files only); returns how many."""
    n = 0
    for f in previous_run_files(out):
        if f.is_file() or f.is_symlink():
            f.unlink()
            n += 1
        elif f.name == FIRST_PASS_DIR and f.is_dir():
            shutil.rmtree(f)
            n += 1
    return n


def restore_first_pass(out: Path, drop_others: bool = True) -> None:
    """Put a first pass's files back in ``out`` and remove ``out/first_pass/``. ``drop_others``: a second pass's files
    of the names the first pass did not write go too (after a second pass; not when keeping the first pass failed
    part way, where the files still in ``out`` are the first pass's own)."""
    src = Path(out) / FIRST_PASS_DIR
    for name in RUN_FILES:
        if (src / name).exists():
            os.replace(src / name, Path(out) / name)
        elif drop_others:
            (Path(out) / name).unlink(missing_ok=True)
    shutil.rmtree(src, ignore_errors=True)


def keep_first_pass(out: Path) -> Path:
    """Move a finished first pass's files into ``out/first_pass/`` (an earlier one there is replaced); returns it."""
    dest = Path(out) / FIRST_PASS_DIR
    if dest.is_dir():
        shutil.rmtree(dest)
    dest.mkdir()
    for name in RUN_FILES:
        f = Path(out) / name
        if f.exists() or f.is_symlink():
            os.replace(f, dest / name)
    return dest
