"""Command line: ``python -m windowvo.config_doc [--write FILE | --check FILE]`` (see :mod:`windowvo.tools.config_doc`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import ConfigError
from ..tools.config_doc import END, REGENERATE, START, generate_reference, reference_in, replace_between_markers


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m windowvo.config_doc",
                                description="Print the config reference generated from windowvo/config.py, or "
                                            "write it into a markdown file between its markers.")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", metavar="FILE", help=f"replace the text between {START} and {END} in FILE")
    g.add_argument("--check", metavar="FILE", help="exit with 1 when FILE's reference differs from the generated one")
    a = p.parse_args(argv)
    try:
        body = generate_reference()
        if a.write or a.check:
            path = Path(a.write or a.check)
            try:
                text = path.read_text()
            except OSError as err:
                raise ConfigError(f"cannot read {path}: {err}") from None
            if a.check:
                if reference_in(text, path.name) != body:
                    print(f"windowvo.config_doc: {path} has a stale config reference; run: {REGENERATE}",
                          file=sys.stderr)
                    return 1
                return 0
            new = replace_between_markers(text, body, path.name)
            if new != text:
                path.write_text(new)
            return 0
    except ConfigError as err:
        print(f"windowvo.config_doc: error: {err}", file=sys.stderr)
        return 2
    sys.stdout.write(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
