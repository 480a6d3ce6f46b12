"""The renderer's arithmetic in a fixed order: a sequence renders to the same files on every x86-64 CPU with AVX2.

numpy's ``@``, ``np.dot`` and a vector's ``np.linalg.norm`` go to the BLAS library, whose kernels OpenBLAS picks for
the CPU at run time (Haswell, SkylakeX, Zen, ...) and which sum in different orders, with or without fused
multiply-adds; numpy's own ``log2``, ``**`` and ``arctan2`` have SIMD code per CPU (AVX-512, AVX2, SSE) too. Their
last bits differ from one machine to the next. In a rendered image that moves a few pixels by a grey level, and a run
on those images moves by 10-30% of its ATE (the rocking figure eight of ``tests/test_metric_scale.py``: 0.0156 m on
the renders of OpenBLAS's AVX-512 kernels, 0.0166 m on the others'): a test or a benchmark would measure the machine.
These functions compute the same results with numpy's elementwise ``+ - * /`` alone (each rounded once, in a fixed
order: IEEE arithmetic, the same on every CPU) or, for the few headings of a scene, the C library's ``atan2``
(correctly rounded in glibc). ``tests/test_synth_exact.py`` renders under other BLAS kernels and numpy SIMD levels
and compares the files. Not covered: OpenCV's own SIMD paths (its remap and filters), which differ on CPUs without
AVX2, and other architectures (ARM), which were not tried.
"""

from __future__ import annotations

import math

import numpy as np

LN2 = math.log(2.0)
LOG_SERIES_TERMS = 10  # u < 1/3: the series' remainder below (1/9)^10 / 21, about 1e-11


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a short inner dimension (3 or 4: points, rays, poses): ``a`` (..., m, k) or (k,), ``b`` (k, n)
    or (k,), in the dtype ``a @ b`` would have."""
    a, b = np.asarray(a), np.asarray(b)
    dtype = np.result_type(a, b)
    a, b = a.astype(dtype, copy=False), b.astype(dtype, copy=False)
    k = a.shape[-1]
    if b.ndim > 2 or b.shape[0] != k:
        raise ValueError(f"matmul: shapes {a.shape} and {b.shape} do not multiply (b: a vector or a matrix)")
    if b.ndim == 1:  # (..., k) @ (k,) -> (...)
        out = a[..., 0] * b[0]
        for j in range(1, k):
            out = out + a[..., j] * b[j]
        return out
    if a.ndim == 1:  # (k,) @ (k, n) -> (n,)
        return matmul(b.T, a)
    out = a[..., :, 0:1] * b[0]
    for j in range(1, k):
        out = out + a[..., :, j:j + 1] * b[j]
    return out


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """The dot product of two vectors."""
    return float(matmul(np.asarray(a), np.asarray(b)))


def rowwise_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(a * b).sum(-1)`` of two (..., k) arrays, the terms added in order."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape[-1] != b.shape[-1]:
        raise ValueError(f"rowwise_dot: last dimensions of {a.shape} and {b.shape} differ")
    out = a[..., 0] * b[..., 0]
    for j in range(1, a.shape[-1]):
        out = out + a[..., j] * b[..., j]
    return out


def norm(v: np.ndarray) -> float:
    """The Euclidean length of a vector."""
    v = np.asarray(v, dtype=float)
    return float(np.sqrt(rowwise_dot(v, v)))


def log2(x: np.ndarray) -> np.ndarray:
    """``np.log2`` of positive values to about 1e-9 (float64), from the exponent ``np.frexp`` splits off and a series
    in the mantissa: numpy's own log2 has SIMD code per CPU (AVX-512, AVX2, SSE) whose last bits differ."""
    x = np.asarray(x, dtype=np.float64)
    m, e = np.frexp(x)  # x = m 2^e, m in [0.5, 1): exact
    m = 2.0 * m  # [1, 2)
    u = (m - 1.0) / (m + 1.0)  # ln m = 2 atanh(u), u in [0, 1/3)
    u2 = u * u
    series = np.zeros_like(u)
    for k in range(LOG_SERIES_TERMS - 1, -1, -1):  # Horner: 1/1 + u2/3 + u2^2/5 + ...
        series = series * u2 + 1.0 / (2 * k + 1)
    return (e - 1.0) + (2.0 * u * series) / LN2


def arctan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``np.arctan2`` element by element through the C library's atan2 (correctly rounded in glibc, the same on every
    CPU; numpy's has SIMD code per CPU). For the scenes' and paths' headings: a few thousand values at most."""
    y, x = np.broadcast_arrays(np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64))
    return np.array([math.atan2(a, b) for a, b in zip(y.ravel().tolist(), x.ravel().tolist())]).reshape(y.shape)


def inv_T(T: np.ndarray) -> np.ndarray:
    """The inverse of a 4x4 rigid transform."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -matmul(R.T, T[:3, 3])
    return Ti
