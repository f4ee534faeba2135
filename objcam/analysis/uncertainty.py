"""Per-texel uncertainty and gain images (the method's Section 5).

- :func:`texel_uncertainty`: ``sigma_j = sqrt(diag(Q_r^{-1}))_j`` with ``Q_r = A^T A + lr I`` (the smoothness
  prior left out, as in the method): the standard deviation of the ridge estimate of texel j per unit
  standard deviation of i.i.d. pixel noise (multiply by the noise level ``sigma`` to get radiance units; pass
  ``sigma=``). From the Cholesky factor ``Q_r = L L^T``: ``Q_r^{-1} = L^{-T} L^{-1}``, so
  ``diag(Q_r^{-1})_j = ||column j of L^{-1}||^2`` with ``L^{-1}`` from one triangular inversion (N^3/3 flops,
  exact, no general inverse). :func:`inverse_diagonal` does the same for any symmetric positive definite Q, in
  float32 where asked (twice the rate, half the memory) and in place: the verdict's Q at 128 x 256.
- :func:`gain_images`: rows of ``G = (A^T A + R)^{-1} A^T`` for chosen texels, ``R = ls D^T D + lr I``
  (:func:`regularizer`): row j tells how much texel j's estimate moves per unit change of each pixel (the
  linear, unconstrained part of the solve). Only the asked rows are solved: ``G[j] = (Q^{-1} e_j)^T A^T``.
- :func:`to_grid` / :func:`scatter_to_image` put per-texel / per-pixel vectors back on the envmap grid / the
  (pooled) image.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.linalg import lapack

from objcam.analysis.leverage import BLOCK_BYTES, _add_prior, _check_A, _gram, _row_blocks, ridge_cholesky
from objcam.envmap import EnvGrid
from objcam.threads import blas_threads, single_blas_thread


def texel_uncertainty(A: np.ndarray | None, lr: float, *, L: np.ndarray | None = None,
                      G: np.ndarray | None = None, sigma: float = 1.0) -> np.ndarray:
    """``sigma * sqrt(diag((A^T A + lr I)^{-1}))`` (N,) float64; ``lr`` absolute.

    Give ``L`` (:func:`objcam.analysis.ridge_cholesky`) to reuse a factorisation, or ``G = A^T A`` (then ``A``
    may be None). Grows as ``lr`` shrinks and for texels whose columns of A are small or nearly collinear with
    others; bounded by ``sigma / sqrt(lr)``.
    """
    if L is None:
        L = ridge_cholesky(A, lr, G=G)
    L = np.asfortranarray(L, dtype=np.float64)
    with single_blas_thread():
        Linv, info = lapack.dtrtri(L, lower=1, overwrite_c=0)
    if info != 0:
        raise ValueError(f"triangular inversion failed (info={info}): A^T A + lr I is singular")
    var = np.einsum("ij,ij->j", Linv, Linv)
    return float(sigma) * np.sqrt(var)


def inverse_diagonal(Q: np.ndarray, overwrite: bool = False, threads: int = 1,
                     last: int | None = None) -> np.ndarray:
    """The last ``last`` entries (default all N) of ``diag(Q^-1)``, float64, of a symmetric positive definite ``Q``
    (N, N), float32 or float64, computed in Q's precision: its Cholesky factor ``Q = L L^T`` (LAPACK potrf) and
    the inverse of its trailing m x m block (trtri): that block is the factor of the Schur complement S of the
    leading rows, and ``(Q^-1)`` restricted to the last m is ``S^-1``, so ``diag(Q^-1)_j = ||column j of
    L_mm^-1||^2`` (the squares summed in float64). N^3 / 3 + m^3 / 3 flops (put the texels wanted last); with
    ``overwrite`` a C- or Fortran-ordered Q is factorised and inverted in place (destroyed: no second N x N
    array), else copied.
    ``threads``: BLAS threads for the two calls (one large factorisation, unlike the solver's many small ones).
    Raises numpy.linalg.LinAlgError when Q is not positive definite in its precision.

    Error: Cholesky's backward error is componentwise, ``|dQ_ij| <= c N eps sqrt(Q_ii Q_jj)`` (eps 6e-8 in
    float32, 1e-16 in float64), so the relative error of ``diag(Q^-1)`` is about ``N eps`` times the condition
    number of Q scaled to a unit diagonal (measured for the verdict: bench/results.md, issue 26, session 19)."""
    Q = np.asarray(Q)
    if Q.ndim != 2 or Q.shape[0] != Q.shape[1] or Q.dtype not in (np.float32, np.float64):
        raise ValueError(f"Q must be a square float32 or float64 matrix, got {Q.dtype} {Q.shape}")
    if last == 0:
        return np.empty(0, dtype=np.float64)
    # a symmetric C-ordered Q is its own transpose in Fortran order: LAPACK works on it in place
    M = Q.T if Q.flags.c_contiguous else Q
    if not (overwrite and M.flags.f_contiguous and M.flags.writeable):
        M = np.array(Q, order="F", copy=True)
    potrf, trtri = lapack.get_lapack_funcs(("potrf", "trtri"), (M,))
    with blas_threads(threads):
        L, info = potrf(M, lower=1, overwrite_a=1, clean=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"not positive definite in {M.dtype} (potrf info={info})")
        n = L.shape[0]
        m = n if last is None else int(last)
        # the trailing block: a view (no copy) when it is the whole factor, else an m x m copy
        Linv, info = trtri(L if m == n else L[n - m :, n - m :], lower=1, overwrite_c=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"triangular inversion failed (trtri info={info})")
    n = Linv.shape[0]
    var = np.empty(n, dtype=np.float64)
    step = 256  # columns of L^-1 (lower triangular: rows c0.. only) squared in float64, 34 MB at a time
    for c0 in range(0, n, step):
        blk = np.asarray(Linv[c0:, c0 : c0 + step], dtype=np.float64)
        var[c0 : c0 + step] = np.einsum("ij,ij->j", blk, blk)
    return var


def to_grid(values: np.ndarray, grid: EnvGrid, texel_index: np.ndarray, fill: float = np.nan) -> np.ndarray:
    """Scatter per-texel ``values`` (N,) or (N, C) at flat ``texel_index`` (N,) onto ``grid``: (H, W[, C]),
    ``fill`` where no texel was kept."""
    values = np.asarray(values)
    texel_index = np.asarray(texel_index, dtype=np.int64).ravel()
    if values.shape[0] != texel_index.size:
        raise ValueError(f"{values.shape[0]} values for {texel_index.size} texels")
    dtype = np.result_type(values.dtype, np.float32) if np.isnan(fill) else values.dtype
    out = np.full((grid.n_texels,) + values.shape[1:], fill, dtype=dtype)
    out[texel_index] = values
    return out.reshape(grid.shape + values.shape[1:])


def scatter_to_image(values: np.ndarray, pixel_index: np.ndarray, image_shape: tuple[int, int],
                     fill: float = np.nan) -> np.ndarray:
    """Per-pixel ``values`` (..., M) at flat ``pixel_index`` (M,) (row * width + col of the pooled image) into
    images (..., H, W), ``fill`` at pixels that are not rows of A (e.g. excluded or outside the mask)."""
    values = np.asarray(values)
    pixel_index = np.asarray(pixel_index, dtype=np.int64).ravel()
    h, w = (int(s) for s in image_shape)
    if values.shape[-1] != pixel_index.size:
        raise ValueError(f"{values.shape[-1]} values for {pixel_index.size} pixels")
    if pixel_index.size and (pixel_index.min() < 0 or pixel_index.max() >= h * w):
        raise ValueError(f"pixel_index out of range for a {h}x{w} image")
    out = np.full(values.shape[:-1] + (h * w,), fill, dtype=np.result_type(values.dtype, np.float32))
    out[..., pixel_index] = values
    return out.reshape(values.shape[:-1] + (h, w))


def texel_columns(texel_index: np.ndarray, flat_texels) -> np.ndarray:
    """Columns of A (positions in ``texel_index``) of grid texels given by flat index ``r * W + c``."""
    texel_index = np.asarray(texel_index, dtype=np.int64).ravel()
    flat = np.atleast_1d(np.asarray(flat_texels, dtype=np.int64))
    order = np.argsort(texel_index)
    pos = np.searchsorted(texel_index, flat, sorter=order)
    pos = np.clip(pos, 0, texel_index.size - 1)
    cols = order[pos]
    bad = texel_index[cols] != flat
    if bad.any():
        raise ValueError(f"texels {flat[bad].tolist()} are not kept columns of A")
    return cols


def regularizer(grid: EnvGrid, texel_index: np.ndarray, ls: float, lr: float) -> sp.csr_matrix:
    """``R = ls D^T D + lr I`` (N, N) sparse float64 with objcam's difference operator and absolute weights
    (convert relative ones with :func:`objcam.solvers.absolute_weights`)."""
    from objcam.solvers.regularization import difference_operator

    n = np.asarray(texel_index).size
    R = sp.identity(n, format="csr", dtype=np.float64) * float(lr)
    if ls > 0:
        D = difference_operator(grid, texel_index)
        R = (R + float(ls) * (D.T @ D)).tocsr()
    return R


def gain_images(A: np.ndarray, R, texels, *, G: np.ndarray | None = None,
                block_bytes: int = BLOCK_BYTES) -> np.ndarray:
    """Rows ``texels`` of the gain matrix ``(A^T A + R)^{-1} A^T``: (len(texels), M) float64.

    ``texels``: column indices of A (see :func:`texel_columns` to convert grid texels). ``R``: (N, N) dense or
    sparse (see :func:`regularizer`), or a scalar meaning ``R = R * I``. ``G = A^T A`` skips forming it.
    Row j has units of texel radiance per pixel value; scatter it with :func:`scatter_to_image`.
    """
    A = _check_A(A)
    n = A.shape[1]
    cols = np.atleast_1d(np.asarray(texels, dtype=np.int64))
    if cols.size and (cols.min() < 0 or cols.max() >= n):
        raise ValueError(f"texel columns out of range [0, {n})")
    with single_blas_thread():
        Q = np.array(_gram(A) if G is None else G, dtype=np.float64, order="F", copy=True)
        _add_prior(Q, R)
        try:
            cf = sla.cho_factor(Q, lower=True, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise ValueError(f"A^T A + R is not positive definite ({err})") from err
        E = np.zeros((n, cols.size), dtype=np.float64, order="F")
        E[cols, np.arange(cols.size)] = 1.0
        V = sla.cho_solve(cf, E, overwrite_b=True, check_finite=False)  # (N, k) = Q^{-1} e_j
        out = np.empty((cols.size, A.shape[0]), dtype=np.float64)
        for r0, blk in _row_blocks(A, block_bytes):
            out[:, r0 : r0 + blk.shape[0]] = (blk @ V).T
    return out
