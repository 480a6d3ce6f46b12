"""``python -m windowvo.view``: the command line lives in :mod:`windowvo.cli.view`."""

import sys

from .cli.view import main

if __name__ == "__main__":
    sys.exit(main())
