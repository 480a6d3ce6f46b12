"""The single exception root of windowvo.

Every error that windowvo raises on purpose derives from :class:`WindowVOError`, so the
command line can print one clear line and exit with code 2 instead of a traceback.
"""

from __future__ import annotations

import sys

# Control characters (a user's key or file name holding a newline, say) are shown escaped: a message stays one line.
ONE_LINE = {c: f"\\x{c:02x}" for c in range(32)} | {10: "\\n", 13: "\\r", 9: "\\t"}


def one_line(text: str) -> str:
    """``text`` with its control characters escaped."""
    return text.translate(ONE_LINE)


class WindowVOError(Exception):
    """Root of all windowvo errors; its message is always one line."""

    def __str__(self) -> str:
        return one_line(super().__str__())


class ConfigError(WindowVOError):
    """The configuration is malformed: unknown key, wrong type or impossible value."""


class SequenceError(WindowVOError):
    """The input sequence folder is missing, incomplete or inconsistent."""


class CalibrationError(SequenceError):
    """The camera calibration is malformed or physically impossible."""


class FrameError(WindowVOError):
    """A single frame could not be used (unreadable, black, duplicated); the run goes on."""


def cli_error(err: object, prog: str = "windowvo") -> int:
    """What every command line does with a known error: one line on stderr, exit code 2."""
    print(f"{prog}: error: {one_line(str(err))}", file=sys.stderr)
    return 2
