"""``python -m windowvo.topics``: the command line lives in :mod:`windowvo.cli.topics`."""

import sys

from .cli.topics import main

if __name__ == "__main__":
    sys.exit(main())
