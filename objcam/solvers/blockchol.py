"""Cholesky factors of free blocks for the exact solver (objcam.solvers.nnls): a factorisation with a jitter
fallback and iterative refinement (:class:`Factor`), the gather of a free block (:func:`free_block`), and free
blocks solved from an earlier block's factor by bordered updates (:class:`UpdatedFree`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from objcam.solvers import nogil


class Factor:
    """Cholesky of a symmetric block with a jitter fallback and iterative refinement.

    ``remake``: a function returning S again; given, S is factorised in place (its memory becomes the factor:
    one |F| x |F| matrix per free block instead of two) and an attempt that fails takes a fresh S from it; the
    refinement's residual then comes from :meth:`solve`'s ``residual``."""

    def __init__(self, S: np.ndarray, jitter0: float = 1e-13, remake=None):
        self.S = None if remake is not None else S
        self.jitter = 0.0
        # S is symmetric: hand LAPACK its transpose, a Fortran-ordered view of the same matrix (a plain copy
        # inside the wrapper instead of a transposing one; none at all when it may overwrite S)
        c, info = nogil.potrf(S.T if S.flags.c_contiguous else S, overwrite=remake is not None)
        if info != 0:
            S = remake() if remake is not None else S
            dmax = float(np.max(np.abs(np.diag(S)))) if S.size else 1.0
            dmax = dmax if dmax > 0 else 1.0
            rel = jitter0
            while info != 0:
                self.jitter = rel * dmax
                Sj = S.copy()
                Sj[np.diag_indices_from(Sj)] += self.jitter
                c, info = nogil.potrf(Sj, overwrite=True)
                rel *= 100.0
                if rel > 1e3:
                    raise np.linalg.LinAlgError("free block is not positive semi-definite")
        self.c = c

    def _solve(self, R: np.ndarray) -> np.ndarray:
        x, info = nogil.potrs(self.c, R)
        if info != 0:
            raise np.linalg.LinAlgError(f"dpotrs failed ({info})")
        return x

    def solve(self, R: np.ndarray, refine: int = 2, residual=None) -> np.ndarray:
        """S^-1 R with ``refine`` steps of iterative refinement; ``residual(x)``: R - S x (required when S was
        factorised in place)."""
        x = self._solve(R)
        for _ in range(refine):
            x = x + self._solve(R - self.S @ x if residual is None else residual(x))
        return x


#: bytes of Q's rows gathered at a time into a free block (objcam.solvers.blockchol.free_block)
BAND_BYTES = 64 * 2**20


def free_block(Q: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Q[idx][:, idx] (|F|, |F|), gathered a band of rows at a time: no |F| x N intermediate (0.7 GB per free
    block at 128 x 256)."""
    k = idx.size
    S = np.empty((k, k))
    step = max(1, BAND_BYTES // (8 * max(Q.shape[0], 1)))
    for r0 in range(0, k, step):
        # mode="clip" (idx is in range): numpy buffers ``out`` under the default mode="raise", a second copy of
        # the band; unbuffered, the gather took half the CPU at 64 x 128 (bench/results.md, issue 26 session 17)
        band = Q.take(idx[r0 : r0 + step], axis=0, mode="clip")
        np.take(band, idx, axis=1, out=S[r0 : r0 + step], mode="clip")
    return S


def free_groups(F: np.ndarray, cols) -> dict[bytes, list[int]]:
    """The columns of ``cols`` grouped by identical free sets F[:, c] (F (N, m) bool), keyed by the packed set."""
    keys: dict[bytes, list[int]] = {}
    for c in cols:
        keys.setdefault(np.packbits(F[:, c]).tobytes(), []).append(int(c))
    return keys


#: a free block F is solved from an earlier block's Cholesky factor over a set S (:class:`UpdatedFree`) when the
#: variables to add (F \\ S) and to hold at zero (S \\ F) number at most this share of |F| (else a fresh
#: factorisation): an update costs ~|S|^2 of triangular solves per such variable, a factorisation |F|^3 / 3, so
#: ~1/3 is the flop break-even; kept below it. Measured at 32 x 64 (two captures, load 5-7; bench/results.md,
#: issue 26 session 19): 0.05-1 tie on the dumped solves; in the stage 0.25 took forest's solve from a median
#: 0.85 to 0.72 CPU s (0.1: 0.70), courtyard's unchanged (0.54; 0.1: 0.58)
CHOL_UPDATE_SHARE = 0.25


@dataclass
class CholBase:
    """A Cholesky factor ``Q_SS = U^T U`` (U (s, s) upper, Fortran order) over the ordered variables S (s,)."""

    S: np.ndarray
    U: np.ndarray


class UpdatedFree:
    """Per-block Cholesky solves that reuse the factors of earlier blocks of the same solve.

    Between pivoting rounds a column's free set changes by a few variables, and the colour columns' free sets
    differ by a few. A new free set F is solved from the stored factor over S closest to it (fewest variables
    to add and to hold at zero): the added variables A are appended by a bordered factor
    ``[[U, K], [0, chol(Q_AA - K^T K)]]`` with ``K = U^-T Q_SA``, and the variables Z = S \\ F held at zero by the
    Schur complement over Z, as nnls's ``_SchurFree`` does for the whole Q (``W = U^-T E_Z``,
    ``(Q^-1)_ZZ = W^T W``). The result is F's exact block solution to rounding, refined once against Q like the
    fresh factorisation's. A set too far from every stored factor (:data:`CHOL_UPDATE_SHARE`) gets a fresh
    factorisation, stored for later blocks. Factors live for one ``solve_exact`` (a reweighted solve has a new
    Q: nothing carries over)."""

    def __init__(self, Q: np.ndarray, B: np.ndarray, stats, fresh: Callable[..., None]):
        # stats: nnls._Stats (factorizations, max_jitter, largest_block, chol_updates are counted);
        # fresh(F, group, X, G, fac=None): the per-block solve of nnls, for the blocks this class hands back
        self.Q, self.B, self.stats, self.fresh = Q, B, stats, fresh
        self.bases: dict[int, CholBase] = {}  # column -> the factor its last block was solved with

    def _closest(self, inF: np.ndarray, nf: int) -> tuple[CholBase | None, int]:
        """The stored base with the fewest added + zeroed variables for the free set ``inF`` (N,) bool, and
        that count."""
        best, cost = None, nf + 1
        for base in {id(b): b for b in self.bases.values()}.values():
            inS = inF[base.S]
            c = int(base.S.size - inS.sum()) + (nf - int(inS.sum()))  # |S \ F| + |F \ S|
            if c < cost:
                best, cost = base, c
        return best, cost

    def _border(self, base: CholBase, add: np.ndarray) -> CholBase | None:
        """base extended by the variables ``add``; None when their Schur complement is not positive definite."""
        s, a = base.S.size, add.size
        K = nogil.trtrs(base.U, self.Q[np.ix_(base.S, add)], trans=True)
        Saa = free_block(self.Q, add) - K.T @ K
        Uaa, info = nogil.potrf(Saa, overwrite=True)
        if info != 0:
            return None
        U = np.zeros((s + a, s + a), order="F")
        U[:s, :s] = base.U
        U[:s, s:] = K
        U[s:, s:] = Uaa
        return CholBase(np.concatenate([base.S, add]), U)

    def __call__(self, F: np.ndarray, cols, X: np.ndarray, G: np.ndarray) -> None:
        Q, B, stats = self.Q, self.B, self.stats
        for group in free_groups(F, cols).values():
            inF = F[:, group[0]]
            idx = np.flatnonzero(inF)
            X[:, group] = 0.0
            if idx.size == 0:
                G[:, group] = -B[:, group]
                continue
            base, cost = self._closest(inF, idx.size)
            if base is not None and 0 < cost <= CHOL_UPDATE_SHARE * idx.size:
                add = idx[~np.isin(idx, base.S, assume_unique=True)]
                base = self._border(base, add) if add.size else base
            elif base is None or cost > 0:
                base = None
            if base is None:  # a fresh factorisation (with Factor's jitter fallback when singular)
                fac = Factor(free_block(Q, idx), remake=lambda: free_block(Q, idx))
                stats.factorizations += 1
                stats.max_jitter = max(stats.max_jitter, fac.jitter)
                if fac.jitter > 0:  # a jittered factor is not Q's: solve with it alone, store nothing
                    self.fresh(F, group, X, G, fac=fac)
                    continue
                base = CholBase(idx, np.asfortranarray(fac.c))
            else:
                stats.chol_updates += 1
            stats.largest_block = max(stats.largest_block, idx.size)
            for c in group:
                self.bases[c] = base
            zpos = np.flatnonzero(~inF[base.S])
            U = base.U
            if zpos.size:
                E = np.zeros((base.S.size, zpos.size))
                E[zpos, np.arange(zpos.size)] = 1.0
                W = nogil.trtrs(U, E, trans=True)
                try:
                    Sz = nogil.cho_factor(W.T @ W)
                except np.linalg.LinAlgError:  # (Q_SS^-1)_ZZ not numerically definite: this block afresh
                    stats.chol_updates -= 1
                    for c in group:
                        del self.bases[c]
                    self.fresh(F, group, X, G)
                    continue

            def constrained(R: np.ndarray) -> np.ndarray:
                """Q_FF^-1 R_F on S's order, 0 on Z (R (s, m))."""
                x, info = nogil.potrs(U, R)
                if zpos.size:
                    mu = -nogil.cho_solve(Sz, x[zpos])
                    x = x + nogil.trtrs(U, W @ mu)
                    x[zpos] = 0.0
                return x

            Bs = B[np.ix_(base.S, group)]
            full = np.zeros((Q.shape[0], len(group)))
            xs = constrained(Bs)
            full[base.S] = xs
            R = Bs - (Q @ full)[base.S]  # one step of iterative refinement against Q, as Factor.solve
            R[zpos] = 0.0
            xs = xs + constrained(R)
            full[base.S] = xs
            X[:, group] = full
            G[:, group] = Q @ full - B[:, group]
