"""The renderer's arithmetic in a fixed order (``windowvo/synth/exact.py``): right, and the same bits on every CPU
(other BLAS kernels and numpy SIMD levels render the same files)."""

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
# probes: the library code the renderer used to call, whose last bits show which kernels ran
rng = np.random.default_rng(0)
a32, v32 = rng.normal(size=(4096, 3)).astype(np.float32), rng.normal(size=3).astype(np.float32)
x = rng.uniform(1e-3, 50.0, 4096)
probe = [a32 @ v32, a32.astype(float) @ v32.astype(float), np.log2(x.astype(np.float32)), np.log2(x),
         np.arctan2(x - 25.0, x[::-1] - 25.0), (x.astype(np.float32) / 50.0) ** 3]
# (the sizes where numpy's SIMD levels changed pixels before: a few frames in 61 of each)
generate_sequence(out / "rocking", SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=3.0, seed=33, vibration_deg=1.0))
generate_sequence(out / "warehouse", SynthSpec.for_scene(SceneKind.WAREHOUSE, path=PathKind.LOOP, duration_s=3.0,
                                                         seed=7, n_moving=1))
generate_sequence(out / "street", SynthSpec.for_scene(SceneKind.STREET, path=PathKind.STRAIGHT, duration_s=0.5,
                                                      seed=9, width=306, height=92, fx=180.0))
files = {str(p.relative_to(out)): hashlib.sha1(p.read_bytes()).hexdigest() for p in sorted(out.rglob("*"))
         if p.is_file()}
print(json.dumps({"probe": hashlib.sha1(b"".join(np.ascontiguousarray(p).tobytes() for p in probe)).hexdigest(),
                  "files": files}))
"""
# numpy's SIMD dispatch above the x86-64 baseline, switched off (numpy >= 2.0 names; an unknown one is ignored)
NUMPY_BASELINE = "X86_V3 X86_V4 AVX512_ICL AVX512_SPR AVX2 FMA3 AVX512F AVX512_SKX"


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
    x = rng.uniform(1e-6, 1e3, 10000)
    np.testing.assert_allclose(exact.log2(x), np.log2(x), rtol=0, atol=1e-9)
    y, z = rng.normal(size=(2, 500))
    np.testing.assert_allclose(exact.arctan2(y, z), np.arctan2(y, z), rtol=0, atol=1e-15)
    for bad in ((np.ones((2, 3)), np.ones((4, 2))), (np.ones((2, 3)), np.ones((3, 3, 3)))):
        with pytest.raises(ValueError):
            exact.matmul(*bad)
    with pytest.raises(ValueError):
        exact.rowwise_dot(np.ones((2, 3)), np.ones((2, 4)))


@pytest.mark.slow
def test_other_kernels_and_simd_levels_render_the_same_files(tmp_path):
    """OpenBLAS picks its kernels by the CPU (AVX-512's sum floats in another order than AVX2's), and numpy's log2,
    power and arctan2 have SIMD code per CPU: a renderer that calls them moves pixels by a grey level between two
    machines (and a run on them by 10-30%). Rendered here as this CPU would (its own kernels), with numpy at the
    x86-64 baseline and OpenBLAS's Prescott (SSE3) kernels, and, on a CPU with AVX-512, OpenBLAS's SkylakeX kernels."""
    variants = {"this CPU": {}, "numpy baseline, Prescott": {"NPY_DISABLE_CPU_FEATURES": NUMPY_BASELINE,
                                                              "OPENBLAS_CORETYPE": "Prescott"}}
    if _cpu_has_avx512():
        variants["SkylakeX"] = {"OPENBLAS_CORETYPE": "SkylakeX"}
    runs = {}
    for name, extra in variants.items():
        env = {**os.environ, **extra}
        proc = subprocess.run([sys.executable, "-c", RENDER, str(tmp_path / name.replace(" ", "_").replace(",", ""))],
                              env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, (name, proc.stderr[-2000:])
        runs[name] = json.loads(proc.stdout.strip().splitlines()[-1])
    if len({r["probe"] for r in runs.values()}) == 1:
        pytest.skip("numpy and its BLAS give the same bits under every variant here: nothing to compare")
    first = runs["this CPU"]["files"]
    assert len(first) > 40
    for name, run in runs.items():
        assert run["files"].keys() == first.keys(), name
        differ = sorted(k for k in first if first[k] != run["files"][k])
        assert not differ, (name, differ)
