"""``python -m windowvo.convert``: the command line lives in :mod:`windowvo.cli.convert`."""

import sys

from .cli.convert import main

if __name__ == "__main__":
    sys.exit(main())
