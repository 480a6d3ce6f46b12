"""``python -m windowvo.bench``: the command line lives in :mod:`windowvo.cli.bench`."""

import sys

from .cli.bench import main

if __name__ == "__main__":
    sys.exit(main())
