"""``python -m windowvo.batch``: the command line lives in :mod:`windowvo.cli.batch`."""

import sys

from .cli.batch import main

if __name__ == "__main__":
    sys.exit(main())
