"""Shared fixtures: rendered synthetic sequences are made once per test session (per worker)."""

from __future__ import annotations

from pathlib import Path

import pytest

from windowvo.config import config_from_dict
from windowvo.synth.generate import SynthSpec, generate_sequence
from windowvo.synth.paths import PathKind

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def seq_factory(tmp_path_factory):
    cache: dict[str, Path] = {}

    def make(name: str, **kw) -> Path:
        if name not in cache:
            out = tmp_path_factory.mktemp(name)
            generate_sequence(out, SynthSpec(**kw))
            cache[name] = out
        return cache[name]

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
