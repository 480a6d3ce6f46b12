"""Command line: ``python -m windowvo.run [CONFIG] [key=value ...]``.

Without CONFIG, runs the embedded default: renders a short synthetic loop (cached under
./windowvo_output/default_sequence), runs VO on it, prints the accuracy and writes the
outputs to ./windowvo_output/default.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from .config import Config, ConfigError, apply_overrides, config_from_dict, load_config
from .errors import WindowVOError, cli_error

log = logging.getLogger("windowvo")

DEFAULT_ROOT = Path("windowvo_output")

EPILOG = """\
examples:
  python -m windowvo.run                                  # embedded default (synthetic loop)
  python -m windowvo.run configs/example.yaml             # your own sequence folder
  python -m windowvo.run configs/example.yaml frontend.max_features=300 viz.rerun=off

A config needs only `sequence:` (a native sequence folder) and `output:`; relative
paths are resolved against the config file. Every other key has a default; see the README's
config reference. Outputs: trajectory.txt (TUM, one line per frame), stats.csv,
config_resolved.yaml, summary.json and recording.rrd (when viz.rerun=save).
Exit codes: 0 done, 2 bad input or configuration, 130 interrupted (results still written).
"""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="windowvo",
        description="windowvo: sliding-window visual odometry (OpenCV front end, GTSAM fixed-lag smoother) "
        "for ground robots, with wheel odometry for metric scale.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", nargs="?", help="YAML config file; omit to run the embedded default")
    p.add_argument("overrides", nargs="*", help="dotted overrides, e.g. frontend.max_features=300")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("-q", "--quiet", action="store_true", help="only warnings and the summary")
    return p


def default_config(overrides: list[str]) -> Config:
    """The embedded default: a rendered synthetic loop with wheel odometry."""
    from .synth.generate import SynthSpec, generate_sequence
    from .synth.paths import PathKind

    seq_dir = DEFAULT_ROOT / "default_sequence"
    spec = SynthSpec(path=PathKind.LOOP, duration_s=25.0, fps=20.0, seed=1)
    marker = seq_dir / "synth.json"
    if not marker.is_file() or json.loads(marker.read_text()).get("seed") != spec.seed or not (
        seq_dir / "odometry.csv"
    ).is_file():
        log.info("rendering the default synthetic sequence into %s (once)", seq_dir)
        generate_sequence(seq_dir, spec)
    data = {"sequence": str(seq_dir.resolve()), "output": str((DEFAULT_ROOT / "default").resolve())}
    data = apply_overrides(data, overrides)
    return config_from_dict(data, base_dir=Path.cwd())


def check_output_folder(out: Path) -> None:
    """Fail early, with one line, when the outputs cannot be written to ``out`` as a folder."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output '{out}' is an existing file; 'output' must be a folder")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ConfigError(f"output '{out}' cannot be created: '{parent}' is a file, not a folder")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise ConfigError(f"output '{out}' cannot be created: '{parent}' is not writable")
            break
    if out.is_dir() and not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(f"output folder '{out}' is not writable")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else (logging.WARNING if args.quiet else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("matplotlib").setLevel(logging.WARNING)
    config_arg = args.config
    overrides = list(args.overrides)
    if config_arg is not None and "=" in config_arg and not Path(config_arg).exists():
        overrides.insert(0, config_arg)
        config_arg = None
    try:
        cfg = load_config(config_arg, overrides) if config_arg else default_config(overrides)
        if args.no_progress:
            cfg.progress = False
        check_output_folder(cfg.output)
        from .runtime.job import run_and_report

        result = run_and_report(cfg)
    except (ConfigError, WindowVOError) as err:
        return cli_error(err)
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
