"""Command-line tools: each module is argparse plus a call into the library (``runtime``, ``tools``, ``eval``,
``viz``); ``python -m windowvo.NAME`` runs ``windowvo.cli.NAME``."""
