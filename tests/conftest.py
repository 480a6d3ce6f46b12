"""Shared fixtures: rendered synthetic sequences are made once per test run, shared by the xdist workers."""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
from pathlib import Path

import pytest

from windowvo.config import config_from_dict
from windowvo.synth.generate import SynthSpec, generate_sequence
from windowvo.synth.paths import PathKind

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _shared_root(tmp_path_factory) -> Path:
    """A folder every pytest-xdist worker of this run sees (the workers' base temp folders' parent),
    so that two workers needing the same sequence render it once; without xdist, the session's own."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "rendered_sequences"
    root.mkdir(parents=True, exist_ok=True)
    return root


def _render_once(root: Path, name: str, spec: SynthSpec) -> Path:
    """Render ``spec`` into ``root/name-<hash of the spec>`` unless a worker already did (a file lock
    serialises the workers; the folder appears only when complete)."""
    key = hashlib.sha1(repr(spec).encode()).hexdigest()[:12]
    out = root / f"{name}-{key}"
    with open(root / f"{name}-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not out.is_dir():
            part = root / f"{name}-{key}.partial"
            shutil.rmtree(part, ignore_errors=True)
            generate_sequence(part, spec)
            part.rename(out)
    return out


@pytest.fixture(scope="session")
def seq_factory(tmp_path_factory):
    """``make(name, **SynthSpec fields)``: a rendered sequence, rendered once per test run (shared by
    tests and xdist workers; keyed by the whole spec, so two specs under one name never mix)."""
    root = _shared_root(tmp_path_factory)
    cache: dict[str, Path] = {}

    def make(name: str, **kw) -> Path:
        spec = SynthSpec(**kw)
        ident = f"{name}:{spec!r}"
        if ident not in cache:
            cache[ident] = _render_once(root, name, spec)
        return cache[ident]

    return make


@pytest.fixture(scope="session")
def short_loop(seq_factory) -> Path:
    return seq_factory("short_loop", path=PathKind.LOOP, duration_s=12.0, seed=5)


def make_config(seq: Path, out: Path, **sections):
    # Sequential by default: the deterministic one-process mode (the pipelined mode is tested against it).
    data = {"sequence": str(seq), "output": str(out), "progress": False, "viz": {"rerun": "off"},
            "run_mode": "sequential"}
    for k, v in sections.items():
        if isinstance(v, dict):
            data.setdefault(k, {}).update(v)
        else:
            data[k] = v
    return config_from_dict(data)
