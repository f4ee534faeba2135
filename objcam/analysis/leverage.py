"""Pixel leverage and Cook's distance of the ridge fit (the method's Section 5), without the M x M hat matrix.

Notation (all per colour channel; a transport ``A`` stored as (C, M, N) is analysed one ``A[c]`` at a time):
``A`` (M, N) pixels x kept texels (float32 or float64; every product is formed in float64), ``lr`` the
*absolute* ridge weight (:func:`absolute_ridge` converts the relative weights objcam's solvers use, i.e.
multiples of ``s = mean(diag(A^T A))``), and

    Q_r = A^T A + lr I        (N, N),        H = A Q_r^{-1} A^T        (M, M, never formed).

The smoothness prior is left out of ``Q_r`` as in the method; ``prior=`` adds any extra symmetric PSD (N, N)
term (e.g. ``ls D^T D``) where a caller wants it in.

Leverage ``h_ii = a_i Q_r^{-1} a_i^T = ||L^{-1} a_i^T||^2`` with ``Q_r = L L^T``: one Cholesky factorisation,
then triangular solves on column blocks of ``A^T`` (M N^2 flops, level-3 BLAS, memory bounded by one block).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from objcam.threads import single_blas_thread

#: Bytes of one float64 work block (rows of A converted to float64 and their solves).
BLOCK_BYTES = 64 * 2**20


def _check_A(A: np.ndarray) -> np.ndarray:
    A = np.asarray(A)
    if A.ndim != 2:
        raise ValueError(f"A must be 2-D (pixels x texels), got shape {A.shape}")
    if A.shape[1] == 0:
        raise ValueError("A has no columns (no kept texels)")
    return A


def block_rows(n: int, block_bytes: int = BLOCK_BYTES) -> int:
    """Rows of A per block so that a float64 block of ``n`` columns stays within ``block_bytes``."""
    return max(1, int(block_bytes) // (8 * max(int(n), 1)))


def _row_blocks(A: np.ndarray, block_bytes: int = BLOCK_BYTES, copy: bool = False):
    """Yield (r0, float64 C-contiguous block of rows of A); a view of A where possible unless ``copy`` (needed
    before anything writes into the block)."""
    step = block_rows(A.shape[1], block_bytes)
    for r0 in range(0, A.shape[0], step):
        blk = A[r0 : r0 + step]
        yield r0, (np.array(blk, dtype=np.float64, order="C", copy=True) if copy
                   else np.ascontiguousarray(blk, dtype=np.float64))


def _gram(A: np.ndarray) -> np.ndarray:
    from objcam.solvers.regularization import gram

    return gram(A)


def column_scale(A: np.ndarray) -> float:
    """``s = mean(diag(A^T A))`` (mean squared column norm), computed blockwise without the Gram matrix."""
    A = _check_A(A)
    tot = 0.0
    for _, blk in _row_blocks(A):
        tot += float(np.einsum("ij,ij->", blk, blk))
    return tot / A.shape[1]


def absolute_ridge(A: np.ndarray | None, lr_rel: float, G: np.ndarray | None = None) -> float:
    """The absolute ridge weight ``lr_rel * mean(diag(A^T A))`` (as :func:`objcam.solvers.absolute_weights`).

    Pass the Gram matrix ``G = A^T A`` when it exists already (then ``A`` may be None).
    """
    if lr_rel < 0:
        raise ValueError("the ridge weight must be >= 0")
    if G is not None:
        s = float(np.mean(np.diag(G))) if G.size else 0.0
    elif A is not None:
        s = column_scale(A)
    else:
        raise ValueError("give A or G")
    return float(lr_rel) * s


def _add_prior(Q: np.ndarray, prior) -> None:
    if prior is None:
        return
    if np.isscalar(prior):
        Q[np.diag_indices_from(Q)] += float(prior)
    elif sp.issparse(prior):
        Q += prior.toarray()
    else:
        P = np.asarray(prior, dtype=np.float64)
        if P.shape != Q.shape:
            raise ValueError(f"prior has shape {P.shape}, expected {Q.shape}")
        Q += P


def cholesky_factor(G: np.ndarray, lr: float, prior=None) -> np.ndarray:
    """Lower Cholesky factor ``L`` (N, N) float64, Fortran order, of ``G + lr I (+ prior)``.

    Raises ValueError when the matrix is not positive definite (e.g. ``lr = 0`` with a rank-deficient A).
    """
    if lr < 0:
        raise ValueError("the ridge weight must be >= 0")
    Q = np.array(G, dtype=np.float64, order="F", copy=True)
    if lr > 0:
        Q[np.diag_indices_from(Q)] += float(lr)
    _add_prior(Q, prior)
    with single_blas_thread():
        try:
            L = sla.cholesky(Q, lower=True, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise ValueError(f"A^T A + lr I is not positive definite ({err}); use a ridge weight lr > 0") from err
    return np.asfortranarray(L)


def ridge_cholesky(A: np.ndarray, lr: float, *, G: np.ndarray | None = None, prior=None) -> np.ndarray:
    """``L`` with ``L L^T = A^T A + lr I (+ prior)``; pass ``G = A^T A`` to skip forming it. Share the result
    between :func:`leverage`, :func:`cooks_distance` and :func:`objcam.analysis.texel_uncertainty` (``L=``)."""
    A = _check_A(A) if A is not None else None
    if G is None:
        if A is None:
            raise ValueError("give A or G")
        with single_blas_thread():
            G = _gram(A)
    return cholesky_factor(G, lr, prior)


def leverage(A: np.ndarray, lr: float, *, L: np.ndarray | None = None, G: np.ndarray | None = None,
             prior=None, block_bytes: int = BLOCK_BYTES) -> np.ndarray:
    """Leverage (M,) float64: the diagonal ``h_ii = a_i (A^T A + lr I)^{-1} a_i^T`` of the ridge hat matrix.

    ``lr`` absolute (see :func:`absolute_ridge`). ``L`` (from :func:`ridge_cholesky`) or ``G = A^T A`` skip the
    factorisation or the Gram matrix. Each block of rows ``A_b`` costs one triangular solve ``L Z = A_b^T`` and
    ``h_b = column sums of Z^2``; memory is bounded by ``block_bytes`` (default 64 MiB) besides ``L``.
    With ``lr > 0``, ``0 <= h_ii < 1`` and ``sum h_ii = sum_k s_k^2 / (s_k^2 + lr)`` (s_k the singular values).
    """
    A = _check_A(A)
    if L is None:
        L = ridge_cholesky(A, lr, G=G, prior=prior)
    L = np.asfortranarray(L, dtype=np.float64)
    if L.shape != (A.shape[1], A.shape[1]):
        raise ValueError(f"L has shape {L.shape}, expected {(A.shape[1],) * 2}")
    h = np.empty(A.shape[0], dtype=np.float64)
    with single_blas_thread():
        for r0, blk in _row_blocks(A, block_bytes, copy=True):
            # blk is our own copy and blk.T is Fortran-contiguous: solved in place
            Z = sla.solve_triangular(L, blk.T, lower=True, overwrite_b=True, check_finite=False)
            h[r0 : r0 + blk.shape[0]] = np.einsum("ij,ij->j", Z, Z)
    return h


def predict(A: np.ndarray, x: np.ndarray, block_bytes: int = BLOCK_BYTES) -> np.ndarray:
    """``A @ x`` in float64, blockwise (no full float64 copy of a float32 A). x (N,) or (N, C)."""
    A = _check_A(A)
    x = np.asarray(x, dtype=np.float64)
    out = np.empty((A.shape[0],) + x.shape[1:], dtype=np.float64)
    with single_blas_thread():
        for r0, blk in _row_blocks(A, block_bytes):
            out[r0 : r0 + blk.shape[0]] = blk @ x
    return out


def cooks_distance(A: np.ndarray, y: np.ndarray, x_hat: np.ndarray, lr: float, *, h: np.ndarray | None = None,
                   L: np.ndarray | None = None, G: np.ndarray | None = None) -> np.ndarray:
    """Cook's distance of every pixel for a fitted envmap: (M,) for ``y`` (M,), ``x_hat`` (N,); or per channel
    (M, C) for ``y`` (M, C), ``x_hat`` (N, C) (a grey A shared by the channels). For a single summary pass the
    luminance of ``y`` and ``x_hat`` (linear, so ``A x_lum`` is the luminance of the prediction when A is grey).

        D_i = e_i^2 / (p s^2) * h_ii / (1 - h_ii)^2

    - ``e = y - A x_hat``: the residual of the fit actually made (e.g. the non-negative, smoothed solve);
    - ``h`` the ridge leverage (:func:`leverage`, computed here unless given);
    - ``p = sum_i h_ii = tr(H)``, the effective number of parameters of the ridge fit (= N for lr = 0 and a
      full-rank A);
    - ``s^2 = ||e||^2 / (M - p)`` per channel, the residual variance with ``M - tr(H)`` residual degrees of
      freedom.

    For ordinary least squares (``lr = 0``, ``x_hat`` the unconstrained fit) this equals the textbook
    definition ``||A x_hat - A x_hat_(i)||^2 / (p s^2)`` with ``x_hat_(i)`` the fit without pixel i. For the
    ridge fit it is the usual ``h_ii`` form (the exact deletion version would have ``(H^2)_ii`` in place of
    the first ``h_ii``), and when ``x_hat`` is the non-negative / smoothness-regularised solve rather than the
    unconstrained ridge fit, ``h`` and ``p`` describe a linearisation of it: the distances are approximate
    and meant for ranking influential pixels, not for F-distribution thresholds.
    """
    A = _check_A(A)
    y = np.asarray(y, dtype=np.float64)
    x_hat = np.asarray(x_hat, dtype=np.float64)
    m = A.shape[0]
    if y.shape[0] != m or x_hat.shape[0] != A.shape[1] or y.shape[1:] != x_hat.shape[1:]:
        raise ValueError(f"shapes do not match: A {A.shape}, y {y.shape}, x_hat {x_hat.shape}")
    if h is None:
        h = leverage(A, lr, L=L, G=G)
    h = np.asarray(h, dtype=np.float64)
    e = y - predict(A, x_hat)
    p = float(h.sum())
    dof = m - p
    if dof <= 0:
        raise ValueError(f"no residual degrees of freedom (M = {m}, p = {p:.3g})")
    s2 = np.einsum("i...,i...->...", e, e) / dof
    hh = h / (1.0 - h) ** 2
    if e.ndim == 2:
        hh = hh[:, None]
    # a perfect fit (s^2 = 0) has no influential pixel: D = 0 there rather than 0/0
    safe = np.where(s2 > 0, s2, 1.0)
    return np.where(s2 > 0, e**2 / (p * safe) * hh, 0.0)
