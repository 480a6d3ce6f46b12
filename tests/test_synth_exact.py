"""The renderer's products summed in a fixed order (``windowvo/synth/exact.py``): right, and the same bits on every
CPU (two BLAS kernels render the same files)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from windowvo.geometry import inv_T as inv_T_blas
from windowvo.synth import exact

RENDER = """
import hashlib, json, sys
from pathlib import Path
import numpy as np
from windowvo.synth.generate import SynthSpec, generate_sequence
from windowvo.synth.paths import PathKind
from windowvo.synth.scenes import SceneKind
out = Path(sys.argv[1])
# a BLAS probe: float32 products of the renderer's shapes, whose last bits show which kernel ran
rng = np.random.default_rng(0)
probe = rng.normal(size=(4096, 3)).astype(np.float32) @ rng.normal(size=3).astype(np.float32)
generate_sequence(out / "rocking", SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=1.0, seed=33, vibration_deg=1.0,
                                             width=240, height=180, fx=130.0))
generate_sequence(out / "street", SynthSpec.for_scene(SceneKind.STREET, path=PathKind.STRAIGHT, duration_s=0.5,
                                                      seed=9, width=306, height=92, fx=180.0))
files = {str(p.relative_to(out)): hashlib.sha1(p.read_bytes()).hexdigest() for p in sorted(out.rglob("*"))
         if p.is_file()}
print(json.dumps({"probe": hashlib.sha1(probe.tobytes()).hexdigest(), "files": files}))
"""


def _cpu_has_avx512() -> bool:
    try:
        return "avx512f" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def test_products_match_numpys():
    rng = np.random.default_rng(1)
    R = rng.normal(size=(3, 3))
    cases = [(rng.normal(size=(50, 3)), R.T), (rng.normal(size=(7, 4, 3)), R), (R, rng.normal(size=3)),
             (rng.normal(size=3), R), (rng.normal(size=(6, 5, 3)).astype(np.float32), rng.normal(size=3).astype(
                 np.float32)), (rng.normal(size=(9, 4)), rng.normal(size=(4, 4)))]
    for a, b in cases:
        want = a @ b
        got = exact.matmul(a, b)
        assert got.shape == want.shape and got.dtype == want.dtype, (a.shape, b.shape)
        np.testing.assert_allclose(got, want, rtol=1e-5 if want.dtype == np.float32 else 1e-12, atol=1e-6)
    v, w = rng.normal(size=3), rng.normal(size=3)
    assert exact.dot(v, w) == pytest.approx(float(v @ w), rel=1e-12)
    assert exact.norm(v) == pytest.approx(float(np.linalg.norm(v)), rel=1e-12)
    np.testing.assert_allclose(exact.rowwise_dot(cases[0][0], cases[0][0]), (cases[0][0] ** 2).sum(axis=1))
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(R)[0]
    T[:3, 3] = rng.normal(size=3)
    np.testing.assert_allclose(exact.inv_T(T), inv_T_blas(T), atol=1e-12)
    np.testing.assert_allclose(exact.matmul(exact.inv_T(T), T), np.eye(4), atol=1e-12)
    with pytest.raises(ValueError):
        exact.matmul(np.ones((2, 3)), np.ones((4, 2)))


def test_two_blas_kernels_render_the_same_files(tmp_path):
    """OpenBLAS picks its kernels by the CPU; AVX-512's sum floats in another order than AVX2's. A renderer whose
    products go through BLAS moves pixels by a grey level between the two (and a run on them by 10-30%)."""
    if not _cpu_has_avx512():
        pytest.skip("this CPU has no AVX-512: OpenBLAS's SkylakeX kernel, the one that differs, cannot run here")
    runs = {}
    for kernel in ("Haswell", "SkylakeX"):
        env = {**os.environ, "OPENBLAS_CORETYPE": kernel}
        proc = subprocess.run([sys.executable, "-c", RENDER, str(tmp_path / kernel)], env=env, capture_output=True,
                              text=True, timeout=300, check=True)
        runs[kernel] = json.loads(proc.stdout.strip().splitlines()[-1])
    if runs["Haswell"]["probe"] == runs["SkylakeX"]["probe"]:
        pytest.skip("numpy's BLAS gives the same bits under both kernels here (not OpenBLAS?): nothing to compare")
    a, b = runs["Haswell"]["files"], runs["SkylakeX"]["files"]
    assert len(a) > 20 and a.keys() == b.keys()
    differ = sorted(k for k in a if a[k] != b[k])
    assert not differ, differ
