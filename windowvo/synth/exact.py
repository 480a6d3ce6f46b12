"""The renderer's small products, summed term by term: the same bits on every CPU.

numpy's ``@``, ``np.dot`` and a vector's ``np.linalg.norm`` go to the BLAS library, whose kernels are chosen for the
CPU at run time (OpenBLAS: Haswell, SkylakeX, Zen, ...) and sum in different orders, with or without fused
multiply-adds: their last bits differ from one machine to the next. In a rendered image that moves a few pixels by a
grey level, and a run on those images moves by 10-30% of its ATE (a rendered figure eight's fused run: 0.0166 m on
one machine's kernels, 0.0156 m on another's): a test or a benchmark would measure the machine. These functions
compute the same products with numpy's elementwise operations alone (each product and sum rounded once, in a fixed
order), which give the same result on every CPU, so a sequence renders to the same images everywhere
(``tests/test_synth_exact.py`` renders under two BLAS kernels and compares the files).
"""

from __future__ import annotations

import numpy as np


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a short inner dimension (3 or 4: points, rays, poses): ``a`` (..., m, k) or (k,), ``b`` (k, n)
    or (k,), in the dtype ``a @ b`` would have."""
    a, b = np.asarray(a), np.asarray(b)
    dtype = np.result_type(a, b)
    a, b = a.astype(dtype, copy=False), b.astype(dtype, copy=False)
    k = a.shape[-1]
    if b.shape[0] != k:
        raise ValueError(f"matmul: inner dimensions {a.shape} and {b.shape} differ")
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
    out = a[..., 0] * b[..., 0]
    for j in range(1, a.shape[-1]):
        out = out + a[..., j] * b[..., j]
    return out


def norm(v: np.ndarray) -> float:
    """The Euclidean length of a vector."""
    v = np.asarray(v, dtype=float)
    return float(np.sqrt(rowwise_dot(v, v)))


def inv_T(T: np.ndarray) -> np.ndarray:
    """The inverse of a 4x4 rigid transform."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -matmul(R.T, T[:3, 3])
    return Ti
