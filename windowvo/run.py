"""``python -m windowvo.run``: the command line lives in :mod:`windowvo.cli.run`."""

import sys

from .cli.run import main

if __name__ == "__main__":
    sys.exit(main())
