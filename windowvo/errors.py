"""The single exception root of windowvo.

Every error that windowvo raises on purpose derives from :class:`WindowVOError`, so the
command line can print one clear line and exit with code 2 instead of a traceback.
"""

from __future__ import annotations


class WindowVOError(Exception):
    """Root of all windowvo errors."""


class ConfigError(WindowVOError):
    """The configuration is malformed: unknown key, wrong type or impossible value."""


class SequenceError(WindowVOError):
    """The input sequence folder is missing, incomplete or inconsistent."""


class CalibrationError(SequenceError):
    """The camera calibration is malformed or physically impossible."""


class FrameError(WindowVOError):
    """A single frame could not be used (unreadable, black, duplicated); the run goes on."""
