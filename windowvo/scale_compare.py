"""``python -m windowvo.scale_compare``: the command line lives in :mod:`windowvo.cli.scale_compare`."""

import sys

from .cli.scale_compare import main

if __name__ == "__main__":
    sys.exit(main())
