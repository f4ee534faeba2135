"""The regularised least-squares problem in Gram form.

objcam solves, per colour channel,

    min_x  ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2,   x >= 0,

with ``A`` (M, N) the light-transport matrix restricted to the kept texels, ``y`` (M,) the photo's pixels and
``x`` (N,) the radiance of the kept texels. The solvers work on the Gram form

    Q = A^T A + ls D^T D + lr I   (N, N) float64,     b = A^T y   (N,) float64,

and minimise ``0.5 x^T Q x - b^T x`` (same minimiser). The full objective is recovered from the Gram form as
``x^T Q x - 2 b^T x + y^T y`` (see :func:`objcam.solvers.nnls.objective`).

Smoothness operator ``D`` (:func:`difference_operator`): one row per pair of 4-neighbouring kept texels --
(r, c)-(r, c+1) with the column wrapping in azimuth, and (r, c)-(r+1, c); there are no edges across the poles.
Each row is ``w (x_i - x_j)`` with the weight chosen so that ``||D x||^2`` is the discrete Dirichlet energy
``integral |grad x|^2 dOmega`` of the radiance on the sphere (in units of radiance^2, independent of the grid
resolution): an edge contributes (difference / centre spacing)^2 * (area it stands for). With dtheta = dphi =
pi/H this gives

    azimuthal edge in row r (centre theta_r):          w^2 = 1 / sin(theta_r)
    polar edge between rows r, r+1 (boundary theta_e): w^2 = sin(theta_e)

so near the poles, where azimuthal neighbours are close together, they are tied more strongly, and the polar
edges there (which stand for little solid angle) count less. At the equator both weights are 1.

Regularisation scaling (:func:`absolute_weights`): ``ls`` and ``lr`` are given *relative* to the data term's
mean curvature ``s = mean(diag(A^T A))`` (the mean squared norm of a column of A): ``ls_abs = ls_rel * s``,
``lr_abs = lr_rel * s``. The defaults therefore do not depend on the number of pixels, the exposure or the
radiance units; ``lr_rel = 1e-3`` means the ridge adds 0.1 % to the average diagonal of ``A^T A``. (They do
depend on the grid resolution, since columns of A scale with texel solid angle: the relative values fix the
conditioning of Q rather than a continuous prior.)
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from objcam.envmap import EnvGrid

#: Default smoothness weight relative to mean(diag(A^T A)).
DEFAULT_LS_REL = 1e-2
#: Default ridge weight relative to mean(diag(A^T A)).
DEFAULT_LR_REL = 1e-4

_GRAM_BLOCK_BYTES = 64 * 2**20


def difference_operator(grid: EnvGrid, texel_index: np.ndarray) -> sp.csr_matrix:
    """Weighted first differences between 4-neighbouring kept texels.

    ``texel_index`` (N,) int: flat indices ``r * W + c`` on ``grid`` of the kept texels, in the column order of A.
    Returns ``D`` (E, N) csr float64, one row ``w * (x_i - x_j)`` per pair of kept neighbours: azimuthal pairs
    (r, c)-(r, (c+1) mod W) with ``w = 1/sqrt(sin theta_r)``, polar pairs (r, c)-(r+1, c) with
    ``w = sqrt(sin theta_edge)``; ``||D x||^2`` approximates the Dirichlet energy of x on the sphere (radiance^2,
    resolution independent; see the module docstring). No edges across the poles.
    """
    texel_index = np.asarray(texel_index, dtype=np.int64).ravel()
    h, w = grid.shape
    n = texel_index.size
    if n and (texel_index.min() < 0 or texel_index.max() >= h * w):
        raise ValueError(f"texel_index out of range for a {h}x{w} grid")
    if np.unique(texel_index).size != n:
        raise ValueError("texel_index holds duplicate texels")
    col_of = np.full(h * w, -1, dtype=np.int64)
    col_of[texel_index] = np.arange(n)
    col_of = col_of.reshape(h, w)

    theta_c = np.pi * (np.arange(h) + 0.5) / h
    theta_e = np.pi * (np.arange(1, h)) / h

    rows_i, rows_j, weights = [], [], []
    # Azimuthal edges, wrapping; with W == 2 the two wrap edges would be the same pair, keep one.
    c0 = np.arange(w if w > 2 else 1)
    i = col_of[:, c0]
    j = col_of[:, (c0 + 1) % w]
    wt = np.broadcast_to((1.0 / np.sqrt(np.sin(theta_c)))[:, None], i.shape)
    rows_i.append(i.ravel()), rows_j.append(j.ravel()), weights.append(wt.ravel())
    # Polar edges.
    if h > 1:
        i = col_of[:-1, :]
        j = col_of[1:, :]
        wt = np.broadcast_to(np.sqrt(np.sin(theta_e))[:, None], i.shape)
        rows_i.append(i.ravel()), rows_j.append(j.ravel()), weights.append(wt.ravel())

    i = np.concatenate(rows_i)
    j = np.concatenate(rows_j)
    wt = np.concatenate(weights)
    keep = (i >= 0) & (j >= 0)
    i, j, wt = i[keep], j[keep], wt[keep]
    e = i.size
    rows = np.repeat(np.arange(e), 2)
    cols = np.stack([i, j], axis=1).ravel()
    vals = np.stack([wt, -wt], axis=1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(e, n))


def _block_rows(n: int) -> int:
    """Rows per block so that a float64 block of N columns stays within _GRAM_BLOCK_BYTES."""
    return max(1, _GRAM_BLOCK_BYTES // (8 * max(n, 1)))


def gram(A: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``A^T A`` as float64 (N, N) for ``A`` (M, N) (float32 or float64); exactly symmetric, C-ordered.

    Accumulated over row blocks of A converted to float64 (at most ~64 MB each), each a BLAS syrk into the upper
    triangle (half a gemm's flops), then mirrored in place: beside the N x N result only one block of extra
    memory (a 2.2 GB Gram at 128 x 256 used to need three: the product and ``0.5 (G + G^T)``'s two
    temporaries). ``out``: an (N, N) float64 C-ordered array to fill (e.g. a memory-mapped file), else new.
    """
    from scipy.linalg.blas import dsyrk

    A = np.asarray(A)
    if A.ndim != 2:
        raise ValueError(f"A must be 2-D, got shape {A.shape}")
    m, n = A.shape
    G = np.zeros((n, n), dtype=np.float64) if out is None else out
    if G.shape != (n, n) or G.dtype != np.float64 or not G.flags.c_contiguous:
        raise ValueError(f"out must be a C-ordered float64 ({n}, {n}) array")
    if out is not None:
        G[...] = 0.0
    # G.T is Fortran-ordered: syrk accumulates into it in place; its upper triangle is G's lower one
    Gf = G.T
    step = _block_rows(n)
    for r0 in range(0, m, step):
        blk = np.asarray(A[r0 : r0 + step], dtype=np.float64)
        if blk.shape[0]:
            dsyrk(1.0, blk, beta=1.0, c=Gf, trans=1, lower=0, overwrite_c=1)
    _mirror_lower(G, step)
    return G


def _mirror_lower(G: np.ndarray, rows: int) -> None:
    """Copy G's lower triangle onto its upper one, in place, ``rows`` rows at a time (no N x N temporary)."""
    n = G.shape[0]
    rows = max(1, min(rows, n))
    for r0 in range(0, n, rows):
        r1 = min(n, r0 + rows)
        d = G[r0:r1, r0:r1]
        il = np.tril_indices(r1 - r0, -1)
        d.T[il] = d[il]
        G[r0:r1, r1:] = G[r1:, r0:r1].T


def rhs(A: np.ndarray, Y: np.ndarray, fast: bool = False) -> np.ndarray:
    """``A^T Y`` as float64: (N,) for ``Y`` (M,), or (N, C) for ``Y`` (M, C). Blocked like :func:`gram`.

    ``fast`` (float32 A only): each block of 2048 rows is multiplied in float32 (Y rounded to float32) and the
    block products are accumulated in float64, ~6x faster; entries to ~1e-7 relative, the precision A is stored in.
    """
    A = np.asarray(A)
    Y = np.asarray(Y)
    squeeze = Y.ndim == 1
    Y2 = Y[:, None] if squeeze else Y
    if Y2.shape[0] != A.shape[0]:
        raise ValueError(f"Y has {Y2.shape[0]} rows, A has {A.shape[0]}")
    m, n = A.shape
    out = np.zeros((n, Y2.shape[1]), dtype=np.float64)
    if fast and A.dtype == np.float32:
        Y32 = np.asarray(Y2, dtype=np.float32)
        for r0 in range(0, m, 2048):
            out += A[r0 : r0 + 2048].T @ Y32[r0 : r0 + 2048]
        return out[:, 0] if squeeze else out
    step = _block_rows(n)
    for r0 in range(0, m, step):
        out += np.asarray(A[r0 : r0 + step], dtype=np.float64).T @ np.asarray(Y2[r0 : r0 + step], dtype=np.float64)
    return out[:, 0] if squeeze else out


def data_scale(G: np.ndarray) -> float:
    """``s = mean(diag(A^T A))`` from the Gram matrix: the unit the relative weights are given in."""
    return float(np.mean(np.diag(G))) if G.size else 0.0


def absolute_weights(G: np.ndarray, ls_rel: float, lr_rel: float) -> tuple[float, float]:
    """(ls_abs, lr_abs) = (ls_rel, lr_rel) * mean(diag(A^T A)); ``G`` is ``A^T A``."""
    if ls_rel < 0 or lr_rel < 0:
        raise ValueError("regularisation weights must be >= 0")
    s = data_scale(G)
    return ls_rel * s, lr_rel * s


def regularized_gram(G: np.ndarray, D: sp.spmatrix | None, ls: float, lr: float | np.ndarray,
                     out: np.ndarray | None = None) -> np.ndarray:
    """``Q = G + ls D^T D + diag(lr)`` (new float64 array, or written into ``out``, an (N, N) float64 buffer
    a reweighted solve reuses so that no second N x N matrix is alive while the next is formed; absolute
    weights; lr a scalar or one per variable, e.g. ``lr k`` on a merged basis whose variable g stands for k_g
    texels)."""
    if out is None:
        Q = np.array(G, dtype=np.float64, copy=True)
    else:
        Q = out
        np.copyto(Q, G)
    if D is not None and ls > 0 and D.shape[0]:
        L = (D.T @ D).tocoo()  # sparse (a few entries per row): add in place, no dense N x N temporary
        L.sum_duplicates()
        Q[L.row, L.col] += ls * L.data
    if np.any(np.asarray(lr) > 0):
        Q[np.diag_indices_from(Q)] += lr
    return Q
