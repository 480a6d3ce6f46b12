"""The embedded default job (a rendered synthetic loop) and the checks made on a job's output folder before
anything runs. Light on imports: the command line uses it before the pipeline is loaded."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from ..config import Config, ConfigError, apply_overrides, config_from_dict
from ..errors import WindowVOError
from .outfolder import check_writable_names, move_aside, previous_run_files, remove_previous
from .progress import Progress

log = logging.getLogger("windowvo")

# Where the embedded default job renders its sequence and writes its outputs (relative to the working folder).
DEFAULT_ROOT = Path("windowvo_output")


def default_config(overrides: list[str], root: Path | None = None) -> Config:
    """The embedded default: a rendered synthetic loop with wheel odometry."""
    from ..synth.generate import SynthSpec, generate_sequence
    from ..synth.paths import PathKind

    root = DEFAULT_ROOT if root is None else root
    seq_dir = root / "default_sequence"
    data = apply_overrides({"sequence": str(seq_dir.resolve()), "output": str((root / "default").resolve())}, overrides)
    cfg = config_from_dict(data, base_dir=Path.cwd())  # a bad override is one line before a minute of rendering
    spec = SynthSpec(path=PathKind.LOOP, duration_s=25.0, fps=20.0, seed=1)
    marker = seq_dir / "synth.json"
    if not marker.is_file() or json.loads(marker.read_text()).get("seed") != spec.seed or not (
        seq_dir / "odometry.csv"
    ).is_file():
        log.info("rendering the default synthetic sequence into %s (once, about a minute)", seq_dir)
        bar = Progress(round(spec.duration_s * spec.fps) + 1, "frames rendered")
        try:
            generate_sequence(seq_dir, spec, progress=lambda n, total: bar.update(n))
        finally:
            bar.close()
    return cfg


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


def prepare_output(out: Path, force: bool, replace: bool) -> None:
    """Never mix two runs' files in one folder: an earlier run's files are deleted (``replace``: the embedded
    default job replaces its own previous run), moved into ``out/previous-<time>/`` (``force``), or the run is
    refused with one line. Call it holding the folder's lock."""
    files = previous_run_files(out)
    if not files:
        return
    if not force:
        check_writable_names(out)
    if replace:
        remove_previous(out)
        log.info("replacing the previous default run in %s", out)
    elif force:
        log.info("--force: the earlier run's files moved to %s", move_aside(out))
    else:
        names = ", ".join(f.name for f in files)
        raise WindowVOError(f"output folder '{out}' holds an earlier run's files ({names}): use --force to move them "
                            f"into {out}/previous-<time>/, --resume to finish a killed run, or another output")
