"""``python -m windowvo.run``: the command line lives in :mod:`windowvo.cli.run`."""

from .runtime import stop

stop.install()  # first: a Ctrl-C while the rest is imported is then handled (one line, exit 130)
from .cli.run import exit_without_teardown, main  # noqa: E402

if __name__ == "__main__":
    exit_without_teardown(main())
