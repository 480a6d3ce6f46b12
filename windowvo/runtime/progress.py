"""Progress of a long step (rendering the default sequence, a run's frames) for a person watching.

On a terminal a ``tqdm`` bar on stderr; elsewhere (CI, a log file, a pipe) one plain line on stderr at every
tenth of the way (``windowvo: frames 120/501 (24%), 21 keyframes``), or every ``LINE_EVERY`` steps when the
total is unknown; a count that goes back (a run made again from its first frame: the wheel clock's second pass)
starts the lines over. ``progress: false`` in the config turns both off.
"""

from __future__ import annotations

import sys
from typing import Any, TextIO

# Steps between two plain lines when the total is not known.
LINE_EVERY = 200


class Progress:
    """``update(n, **extra)`` after each step; ``close()`` at the end."""

    def __init__(self, total: int | None, what: str, enabled: bool = True, stream: TextIO | None = None):
        self.total = total if total and total > 0 else None
        self.what = what
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self._bar: Any = None
        self._next_line = self._step()
        self._last = 0
        if enabled and self.stream.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, unit=what.rstrip("s"), dynamic_ncols=True, file=self.stream)

    def _step(self) -> int:
        return max(1, self.total // 10) if self.total else LINE_EVERY

    def update(self, n: int, **extra: Any) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.n = n
            if extra:
                self._bar.set_postfix(refresh=False, **extra)
            if n % 10 == 0 or n == self.total:
                self._bar.refresh()
            return
        if n < self._last:  # counted from the start again
            self._next_line = self._step()
        self._last = n
        if n < self._next_line:
            return
        while self._next_line <= n:
            self._next_line += self._step()
        share = f" ({100 * n // self.total}%)" if self.total else ""
        more = "".join(f", {v} {k}" for k, v in extra.items())
        total = f"/{self.total}" if self.total else ""
        print(f"windowvo: {self.what} {n}{total}{share}{more}", file=self.stream, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
