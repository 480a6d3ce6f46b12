"""Shared fixtures: rendered synthetic sequences are made once per test run, shared by the xdist workers."""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from windowvo.backend.smoother import SlidingWindowBackend
from windowvo.config import BackendConfig, config_from_dict
from windowvo.eval.metrics import evaluate
from windowvo.io.trajectory import Trajectory
from windowvo.synth.generate import SynthSpec, generate_sequence, pixels_spec
from windowvo.synth.paths import PathKind

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(name: str):
    """The study script ``scripts/<name>.py`` as a module (its ``main(argv)`` and helpers, for its tests)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _shared_root(tmp_path_factory) -> Path:
    """A folder every pytest-xdist worker of this run sees (the workers' base temp folders' parent),
    so that two workers needing the same sequence render it once; without xdist, the session's own."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "rendered_sequences"
    root.mkdir(parents=True, exist_ok=True)
    return root


def _spec_key(spec: SynthSpec) -> str:
    return hashlib.sha1(repr(spec).encode()).hexdigest()[:12]


def _locked_once(root: Path, out: Path, write) -> Path:
    """``write(partial folder)`` unless ``out`` exists (a file lock serialises the workers; the folder appears
    only when complete)."""
    with open(root / f"{out.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not out.is_dir():
            part = root / f"{out.name}.partial"
            shutil.rmtree(part, ignore_errors=True)
            write(part)
            part.rename(out)
    return out


def _render_once(root: Path, spec: SynthSpec) -> Path:
    """The rendered sequence of ``spec``: rendered into ``root/render-<hash of the spec>`` unless a worker
    already did; a spec that differs from a rendered one only in what the estimator is told gets its own
    tables (times, camera.yaml, odometry, ground truth) and a link to that render's images (or to its frames, with
    the spec's frame faults)."""
    pixels = pixels_spec(spec)
    if pixels == spec:
        return _locked_once(root, root / f"render-{_spec_key(spec)}", lambda part: generate_sequence(part, spec))
    images = _render_once(root, pixels) / "images"

    def tables(part: Path) -> None:
        if replace(pixels, wheel=spec.wheel, calib_pitch_error_deg=spec.calib_pitch_error_deg) == spec:
            part.mkdir()
            (part / "images").symlink_to(images, target_is_directory=True)
            generate_sequence(part, replace(spec, write_images=False))
        else:
            generate_sequence(part, spec, images_from=images)

    return _locked_once(root, root / f"tables-{_spec_key(spec)}", tables)


@pytest.fixture(scope="session")
def seq_factory(tmp_path_factory):
    """``make(name, **SynthSpec fields)``: a rendered sequence, rendered once per test run (shared by
    tests and xdist workers; keyed by the whole spec, so two specs under one name never mix and one spec
    under two names is rendered once; ``name`` says what a test uses it for). Do not write into it."""
    root = _shared_root(tmp_path_factory)
    cache: dict[str, Path] = {}

    def make(name: str, **kw) -> Path:
        spec = SynthSpec(**kw)
        ident = repr(spec)
        if ident not in cache:
            cache[ident] = _render_once(root, spec)
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


def run_backend(fs, cfg: BackendConfig, vision: bool = True, backend_cls=None):
    """The back end alone over simulated features (``synth.features``), wheels from the simulation; the
    back end and the keyframes' accuracy against ground truth."""
    be = (backend_cls or SlidingWindowBackend)(fs.world.camera, cfg, use_odometry=True)
    for i, fo in enumerate(fs.keyframes):
        if not vision:
            fo.vision_ok = False
        odom = fs.odometry_step(i)
        be.add_keyframe(fo, odom)
        fo.vision_ok = True
    ts = np.array([f.timestamp for f in fs.keyframes])
    est = Trajectory(ts, np.stack([be.kf_pose[k] for k in range(len(ts))]))
    gt = Trajectory(ts, np.stack(fs.gt_T_world_base))
    return be, evaluate(gt, est)
