"""Blocked dense kernels of the joint solve: products with A' in float64 whatever its dtype, the weighted Gram
matrices ``sum_p A'_p^T diag(w_p) A'_p`` (optionally from float32 products), and a Cholesky factorisation that adds
a diagonal jitter when a matrix is not numerically positive definite.

A' (M, N) is usually float32 (half the memory of the transport); these kernels convert it in row blocks of
~64 MB instead of copying it whole.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.linalg import cho_factor

from objcam.threads import blas_threads

_BLOCK_BYTES = 64 * 2**20


def _rows_per_block(n: int) -> int:
    return max(1, _BLOCK_BYTES // (8 * max(n, 1)))


def matmul(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``A @ X`` in float64 for A (M, N) float32/64 and X (N, k), converting A in row blocks."""
    m, n = A.shape
    out = np.empty((m, X.shape[1]))
    if A.dtype == np.float64:
        return np.matmul(A, X, out=out)
    step = _rows_per_block(n)
    for r0 in range(0, m, step):
        out[r0 : r0 + step] = np.asarray(A[r0 : r0 + step], dtype=np.float64) @ X
    return out


def tmatmul(A: np.ndarray, U: np.ndarray) -> np.ndarray:
    """``A^T @ U`` in float64 for A (M, N) and U (M, k), converting A in row blocks."""
    m, n = A.shape
    if A.dtype == np.float64:
        return A.T @ U
    out = np.zeros((n, U.shape[1]))
    step = _rows_per_block(n)
    for r0 in range(0, m, step):
        out += np.asarray(A[r0 : r0 + step], dtype=np.float64).T @ U[r0 : r0 + step]
    return out


def weighted_gram(As: Sequence[np.ndarray], ws: Sequence[np.ndarray], n: int, fast: bool = False) -> np.ndarray:
    """``sum_p A_p^T diag(w_p) A_p`` (N, N) float64, exactly symmetric; w_p >= 0 (M_p,).

    ``fast=False``: float64 products over row blocks of ~64 MB. ``fast=True`` (float32 A only): each block of
    2048 rows is scaled and multiplied in float32 (sgemm, ~2x faster) and the block products are accumulated in
    float64; the relative error of the entries is ~1e-7 (float32 rounding over 2048-term sums).
    """
    G = np.zeros((n, n))
    for A, w in zip(As, ws):
        sw = np.sqrt(w)
        if fast and A.dtype == np.float32:
            sw32 = sw.astype(np.float32)
            with blas_threads():  # a large product: two threads are 1.6x faster here (objcam.threads)
                for r0 in range(0, A.shape[0], 2048):
                    blk = A[r0 : r0 + 2048] * sw32[r0 : r0 + 2048, None]
                    G += blk.T @ blk
        else:
            step = _rows_per_block(n)
            for r0 in range(0, A.shape[0], step):
                blk = np.asarray(A[r0 : r0 + step], dtype=np.float64) * sw[r0 : r0 + step, None]
                G += blk.T @ blk
    return 0.5 * (G + G.T)


def col_sq_norms(A: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """``diag(A^T diag(w) A)`` (N,) float64."""
    m, n = A.shape
    out = np.zeros(n)
    step = _rows_per_block(n)
    for r0 in range(0, m, step):
        blk = np.asarray(A[r0 : r0 + step], dtype=np.float64)
        sq = blk * blk
        out += sq.sum(axis=0) if w is None else w[r0 : r0 + step] @ sq
    return out


def chol(Q: np.ndarray):
    """``cho_factor`` (upper) of Q (N, N), with a growing diagonal jitter if Q is not numerically positive
    definite; returns (factor, jitter added)."""
    try:
        return cho_factor(Q, lower=False, check_finite=False), 0.0
    except np.linalg.LinAlgError:
        dmax = float(np.max(np.abs(np.diag(Q)))) or 1.0
        rel = 1e-12
        while True:
            try:
                j = rel * dmax
                return cho_factor(Q + j * np.eye(Q.shape[0]), lower=False, check_finite=False), j
            except np.linalg.LinAlgError:
                rel *= 100.0
                if rel > 1e2:
                    raise
