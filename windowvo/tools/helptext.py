"""``--help`` text from a module docstring: the reStructuredText markup (``code``, `code`, ``::``,
``:mod:`x```) a docstring uses for Sphinx, taken out so that a terminal shows plain text."""

from __future__ import annotations

import re

_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")  # :mod:`windowvo.tools.bench` -> windowvo.tools.bench
_LITERAL = re.compile(r"``([^`]*)``|`([^`]*)`")


def plain_help(text: str) -> str:
    """``text`` without reST markup: roles and literals keep their content, a paragraph's closing ``::``
    becomes ``:`` (and a ``::`` alone on its line goes)."""
    out = _ROLE.sub(r"\1", text)
    out = _LITERAL.sub(lambda m: m.group(1) if m.group(1) is not None else m.group(2), out)
    out = re.sub(r"(?m)^\s*::\s*\n", "", out)
    out = re.sub(r"(?m)(\S)::$", r"\1:", out)
    return out.replace("`", "")


def first_line(doc: str | None) -> str:
    """The first line of a docstring, as plain help text (an argparse ``description``)."""
    return plain_help((doc or "").strip().splitlines()[0] if (doc or "").strip() else "")
