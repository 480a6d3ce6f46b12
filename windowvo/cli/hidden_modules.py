"""Modules a command-line run keeps out of its process: pandas.

windowvo never uses pandas, but pyarrow (under rerun) imports it, with numexpr and more, at the recording's
first array conversion whatever is logged: about 0.3 s of CPU on the run's thread before its first frame (a
sixth of a 51-frame KITTI run's start-up, docs/performance.md). pyarrow looks for pandas only to convert pandas
objects, which the recording never logs, and works without it. So ``python -m windowvo.run`` hides pandas from
the import system for as long as it runs (:func:`pandas_hidden`): an import of it fails as if it were not
installed. Only the command-line run does this, never the library (an application that embeds windowvo keeps
its imports), and never when pandas is loaded already.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import sys
from collections.abc import Iterator

HIDDEN = "pandas"


class _Hide(importlib.abc.MetaPathFinder):
    """A finder ahead of all others that refuses ``HIDDEN`` and its submodules."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname == HIDDEN or fullname.startswith(HIDDEN + "."):
            raise ModuleNotFoundError(f"{HIDDEN} is not loaded in a windowvo command-line run "
                                      "(windowvo.cli.hidden_modules)", name=fullname)
        return None


@contextlib.contextmanager
def pandas_hidden() -> Iterator[bool]:
    """Within the block pandas cannot be imported (yields True), unless it is loaded already (yields False:
    nothing is hidden). The finder is removed at the end, so a caller in the same process (a test) can import
    pandas afterwards."""
    if HIDDEN in sys.modules:
        yield False
        return
    finder = _Hide()
    sys.meta_path.insert(0, finder)
    try:
        yield True
    finally:
        with contextlib.suppress(ValueError):
            sys.meta_path.remove(finder)
