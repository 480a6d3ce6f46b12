"""Progress of long steps: a line every tenth of the way when the output is not a terminal."""

from __future__ import annotations

import io

from windowvo.runtime.progress import LINE_EVERY, Progress


def test_a_line_every_tenth_when_not_a_terminal():
    out = io.StringIO()
    p = Progress(501, "frames", stream=out)
    for n in range(1, 502):
        p.update(n, keyframes=n // 6)
    p.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 10, lines
    assert lines[0] == "windowvo: frames 50/501 (9%), 8 keyframes"
    assert lines[-1].startswith("windowvo: frames 500/501 (99%)")


def test_unknown_total_and_disabled():
    out = io.StringIO()
    p = Progress(None, "frames", stream=out)
    for n in range(1, 2 * LINE_EVERY + 1):
        p.update(n)
    assert out.getvalue().splitlines() == [f"windowvo: frames {LINE_EVERY}", f"windowvo: frames {2 * LINE_EVERY}"]
    quiet = io.StringIO()
    q = Progress(100, "frames", enabled=False, stream=quiet)
    for n in range(1, 101):
        q.update(n)
    assert quiet.getvalue() == ""


def test_a_second_pass_starts_the_lines_over():
    """The wheel clock's second pass counts the frames from the first again: its lines are printed too."""
    out = io.StringIO()
    p = Progress(100, "frames", stream=out)
    for _ in range(2):
        for n in range(1, 101):
            p.update(n)
    lines = out.getvalue().splitlines()
    assert len(lines) == 20 and lines[10] == "windowvo: frames 10/100 (10%)", lines
