"""Products with a symmetric matrix that read only the rows a sparse-in-rows operand needs.

The exact solver's free-block iterations multiply the dense Q = G + S (N, N) by vectors that are zero off their
free set; reading only the nonzero rows' part of Q saves the memory traffic that dominates such a product.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import blas

from objcam.solvers import nogil

#: products with Q read only the rows where the vector is nonzero, as runs of contiguous rows (gaps of at most
#: RUNS_GAP zero rows are read through: one BLAS call costs about as much as a few rows); a plain product when
#: more than RUNS_MAX_SHARE of the rows are nonzero or the runs are more than RUNS_MAX
RUNS_GAP = 4
RUNS_MAX_SHARE = 0.95
RUNS_MAX = 256
#: BLAS dsymv per column (objcam.solvers.nogil.symv: one triangle of Q, no packing, GIL released) costs about
#: SYMV_COST x a full read of Q's rows by the row-run products per column: it serves V with
#: ``m SYMV_COST < (share of nonzero rows)``. Measured on one core, 3,136 x 3,136, contiguous free sets: dsymv
#: 1.5 ms per column whatever the share, row runs ~9.5 ms x the share for 2-6 columns (8.4 ms for 3 full
#: columns, 4.5 by dsymv)
SYMV_COST = 0.16


def nonzero_runs(nz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) of the runs of True in ``nz`` (N,) bool, runs closer than RUNS_GAP joined."""
    d = np.diff(np.concatenate(([0], nz.astype(np.int8), [0])))
    s, e = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if s.size > 1:
        keep = np.concatenate(([True], s[1:] - e[:-1] > RUNS_GAP))
        s, e = s[keep], np.concatenate((e[:-1][keep[1:]], e[-1:]))
    return s, e


def sym_dot(Q: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Q V (N, m) for a symmetric Q (N, N) and V (N, m) with few columns, reading only Q's rows where V is nonzero.

    As (V^T Q)^T: the row-major product reads Q ~1.7x faster for a few columns (a 3,131 x 3,131 Q times 3
    columns: 10 against 17 ms on one core). V of a free-block solve is 0 off its free rows: Q V = sum over V's
    runs of nonzero rows of Q[a:b]^T V[a:b], a BLAS product on contiguous rows of Q each, accumulated in place,
    and the zero set's rows are never read (3 columns 69-87% free: 6.9 against 8.3 ms). With few columns and
    most rows nonzero, BLAS dsymv per column is faster still (SYMV_COST): Q must then be exactly symmetric (one
    triangle is read)."""
    nz = np.any(V != 0, axis=1)
    share = nz.mean()
    if (V.shape[1] * SYMV_COST < share and Q.dtype == np.float64
            and (Q.flags.c_contiguous or Q.flags.f_contiguous)):
        return nogil.symv(Q, V)
    starts, ends = nonzero_runs(nz)
    if share > RUNS_MAX_SHARE or starts.size > RUNS_MAX:
        return (np.ascontiguousarray(V.T) @ Q).T
    out = np.zeros(V.shape, order="F")
    for a, b in zip(starts, ends):
        out = blas.dgemm(1.0, Q[a:b].T, V[a:b], beta=1.0, c=out, overwrite_c=1)
    return out


class GramPlusSparse:
    """``Q = G + S`` for the exact solver without forming it: G (N, N) a dense symmetric float64 data Gram,
    shared and never written (the luminance and chroma solves of a target read the same one), S (N, N) a sparse
    symmetric matrix (a reweighting step's prior and ridge). A step's dense Q was a copy of G plus S: one N x N
    array per solve alive at once (1.3 GB at 128 x 256) and a copy per step, where the PCG free blocks of
    objcam.solvers.nnls only need products with Q, its diagonal and a few of its rows.

    Supports what objcam.solvers.nnls uses: ``shape``, ``Q @ X`` (X (N,) or (N, m)), ``take(rows, axis=0)``
    (rows of Q, (|rows|, N)), :meth:`diagonal`, :meth:`restrict` and :meth:`toarray`."""

    ndim = 2
    dtype = np.dtype(np.float64)

    def __init__(self, G: np.ndarray, S):
        import scipy.sparse as sp

        if G.ndim != 2 or G.shape[0] != G.shape[1] or S.shape != G.shape:
            raise ValueError(f"G {G.shape} and S {S.shape} must be the same square shape")
        self.G, self.S = G, sp.csr_matrix(S, dtype=np.float64)
        self.shape = G.shape

    def __matmul__(self, X: np.ndarray) -> np.ndarray:
        X2 = X.reshape(X.shape[0], -1)
        out = sym_dot(self.G, X2)
        out += self.S @ X2
        return out.reshape(X.shape)

    def take(self, rows: np.ndarray, axis: int = 0, mode: str = "raise") -> np.ndarray:
        """Rows ``rows`` of Q (|rows|, N) (axis 0 only: Q is symmetric)."""
        if axis != 0:
            raise ValueError("GramPlusSparse.take: rows only (axis=0)")
        out = self.G.take(rows, axis=0, mode=mode)
        out += self.S[np.asarray(rows)].toarray()
        return out

    def diagonal(self) -> np.ndarray:
        return np.diag(self.G) + self.S.diagonal()

    def restrict(self, idx: np.ndarray) -> "GramPlusSparse":
        """Q[idx][:, idx] as another GramPlusSparse (G's block is copied)."""
        return GramPlusSparse(self.G[np.ix_(idx, idx)], self.S[idx][:, idx])

    def finite(self) -> bool:
        return bool(np.isfinite(self.S.data).all() and _finite_once(self.G))

    def toarray(self) -> np.ndarray:
        """The dense Q (N, N): for the Cholesky paths, which factorise blocks of it."""
        return self.G + self.S.toarray()


def all_finite(a: np.ndarray) -> bool:
    """Whether every entry of ``a`` is finite: one sum (a non-finite entry makes it non-finite), and the
    elementwise test only when the sum is not finite (e.g. overflowed)."""
    return bool(np.isfinite(a.sum()) or np.all(np.isfinite(a)))


_finite: dict[int, object] = {}  # id -> weakref of the data Grams already found finite


def _finite_once(G: np.ndarray) -> bool:
    """Whether G is finite, checked once per array: a reweighted solve's steps all read the same G, which the
    solver never writes (its sum is a full read of G: ~0.1 s a step at 128 x 256)."""
    import weakref

    ref = _finite.get(id(G))
    if ref is not None and ref() is G:
        return True
    ok = all_finite(G)
    if ok:
        try:
            _finite[id(G)] = weakref.ref(G, lambda _r, key=id(G): _finite.pop(key, None))
        except TypeError:  # (not weak-referenceable: checked every time)
            pass
    return ok


def diagonal(Q) -> np.ndarray:
    """Q's diagonal (N,), for a dense Q or a :class:`GramPlusSparse`."""
    return Q.diagonal() if isinstance(Q, GramPlusSparse) else np.diag(Q)


def dot(Q, V: np.ndarray) -> np.ndarray:
    """Q V for a dense symmetric Q (:func:`sym_dot`) or a :class:`GramPlusSparse`."""
    return Q @ V if isinstance(Q, GramPlusSparse) else sym_dot(Q, V)
