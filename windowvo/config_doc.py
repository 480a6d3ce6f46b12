"""``python -m windowvo.config_doc``: the command line lives in :mod:`windowvo.cli.config_doc`."""

import sys

from .cli.config_doc import main

if __name__ == "__main__":
    sys.exit(main())
