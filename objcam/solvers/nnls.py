"""Exact non-negative quadratic programming on the Gram matrix.

``solve_exact`` minimises ``0.5 x^T Q x - b^T x`` subject to ``x >= 0`` for every column ``b`` of ``B`` with one
symmetric positive (semi-)definite ``Q``. It is block principal pivoting (Judice & Pires 1994; the multi
right-hand-side form of Kim & Park 2011, "Fast nonnegative matrix factorization: an active-set-like method"):

* keep a passive (free) set F per column; solve the free block ``Q_FF x_F = b_F`` by Cholesky, set ``x_G = 0``
  and the gradient ``g = Q x - b``;
* the infeasible variables are ``x_i < 0`` in F and ``g_i < 0`` outside F; exchange all of them between the
  sets while their number keeps falling (with 3 retries allowed), otherwise only the one with the largest index
  (Murty's rule, which makes the method finite for positive definite Q);
* columns with the same passive set share one Cholesky factorisation; the first step takes F = everything,
  i.e. the unconstrained solution, which is one factorisation for all columns; on the Schur path
  (:class:`_SchurFree`) a column with many zeros gets its block from the closest earlier factor of the same solve
  when it differs by few variables (:class:`objcam.solvers.blockchol.UpdatedFree`).

Numerics: each free-block solve gets one step of iterative refinement against the original block; a free
block that is not numerically positive definite (Q singular or nearly so, e.g. duplicated columns of A without
regularisation) is factorised with a small diagonal jitter (1e-13 relative to its largest diagonal, growing by
100x until the factorisation succeeds) and then refined against the unjittered block. Variables whose diagonal
``Q_ii`` is zero (<= 1e-20 x the largest: a texel that no pixel sees and no regulariser touches) are fixed at 0;
their gradient is ``-b_i``, which is 0 for a genuine Gram system (b_i > 0 there raises: unbounded). The KKT
residual is always measured on the final clipped x with the original Q, so what is reported is what was achieved.

KKT residual (:func:`kkt_residual`): ``max_i |min(Q_ii x_i, g_i)| / max_i |b_i|`` per column -- the natural
residual of the complementarity problem with x scaled by the diagonal so both arguments are in units of b; it
is 0 exactly at the constrained minimiser.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from objcam.solvers import blockchol, nogil
from objcam.solvers.blockchol import Factor as _Factor, free_block as _free_block, free_groups as _free_groups
from objcam.solvers import multilevel
from objcam.solvers.products import GramPlusSparse, all_finite, diagonal, dot
from objcam.threads import single_blas_thread


@dataclass
class SolveResult:
    """Result of a non-negative quadratic solve.

    x: (N, C) float64 solution (radiance of the kept texels per column / colour channel).
    iterations: ``exact``: rounds of free-block solves (the first is the unconstrained solve, so 1 means no
        pivoting was needed); ``paper``: damped steps taken.
    kkt_residual: (C,) relative KKT residual per column (see :func:`kkt_residual`).
    objective: (C,) objective per column; ``||A x - y||^2 + ls ||D x||^2 + lr ||x||^2`` when y^T y was known
        (solve_envmap), else the Gram-form value ``x^T Q x - 2 b^T x`` (the same up to the constant y^T y).
    seconds: wall time of the solve (excluding forming Q).
    method: "exact" or "paper".
    converged: whether the stopping criterion was met within the iteration limit.
    info: extra details (regularisation weights, factorisations, jitter used, ...).
    """

    x: np.ndarray
    iterations: int
    kkt_residual: np.ndarray
    objective: np.ndarray
    seconds: float
    method: str
    converged: bool = True
    info: dict[str, Any] = field(default_factory=dict)


def _as_2d(B: np.ndarray) -> np.ndarray:
    B = np.asarray(B, dtype=np.float64)
    if B.ndim == 1:
        return B[:, None]
    if B.ndim != 2:
        raise ValueError(f"B must be (N,) or (N, C), got {B.shape}")
    return B


def objective(Q: np.ndarray, B: np.ndarray, X: np.ndarray, yTy: np.ndarray | float | None = None,
              QX: np.ndarray | None = None) -> np.ndarray:
    """Objective per column from the Gram form: ``x^T Q x - 2 b^T x + y^T y``.

    With ``Q = A^T A + ls D^T D + lr I``, ``B = A^T Y`` and ``yTy = ||y||^2`` per column (C,) this equals
    ``||A x - y||^2 + ls ||D x||^2 + lr ||x||^2``. ``yTy=None`` drops the constant. Returns (C,) float64.
    ``QX``: Q X when the caller has it (one product with Q fewer).
    """
    B2, X2 = _as_2d(B), _as_2d(X)
    val = np.einsum("ic,ic->c", X2, Q @ X2 if QX is None else QX) - 2.0 * np.einsum("ic,ic->c", B2, X2)
    if yTy is not None:
        val = val + np.asarray(yTy, dtype=np.float64)
    return val


def kkt_residual(Q: np.ndarray, B: np.ndarray, X: np.ndarray, QX: np.ndarray | None = None) -> np.ndarray:
    """Relative KKT residual per column (C,): ``max_i |min(Q_ii x_i, g_i)| / max_i |b_i|`` with ``g = Q x - b``.

    Zero exactly at the minimiser of ``0.5 x^T Q x - b^T x`` over ``x >= 0`` (x >= 0 is assumed; a negative
    entry counts through ``Q_ii x_i``). A column with ``b = 0`` is scaled by 1. ``QX``: Q X when the caller has it.
    """
    B2, X2 = _as_2d(B), _as_2d(X)
    G = (Q @ X2 if QX is None else QX) - B2
    d = diagonal(Q)[:, None]
    nat = np.abs(np.minimum(d * X2, G))
    # A negative x is infeasible whatever the gradient says.
    nat = np.where(X2 < 0, np.maximum(nat, np.abs(d * X2)), nat)
    scale = np.max(np.abs(B2), axis=0) if B2.shape[0] else np.zeros(B2.shape[1])
    scale = np.where(scale > 0, scale, 1.0)
    return (nat.max(axis=0) if nat.shape[0] else np.zeros(B2.shape[1])) / scale


@dataclass
class _Stats:
    factorizations: int = 0
    max_jitter: float = 0.0
    largest_block: int = 0
    pcg_blocks: int = 0  # free blocks solved by PCG (_PCGFree)
    pcg_fallbacks: int = 0  # of them, handed to Cholesky when PCG stalled
    cg_iterations: int = 0
    pcg_tightened: int = 0  # columns re-solved to PCG_SLACK after a loose round showed nothing infeasible
    pcg_setups: int = 0  # fresh preconditioner set-ups (sparse LU + k solves)
    pcg_updates: int = 0  # preconditioners made from a base's factors by a bordered update (_Bordered)
    chol_updates: int = 0  # free blocks solved from an earlier block's Cholesky factor (blockchol.UpdatedFree)


def _solve_free(Q, B, F, cols, X, G, stats: _Stats, fac: _Factor | None = None) -> None:
    """For each column in ``cols``: x_F = Q_FF^{-1} b_F, x_G = 0, g = Q x - b. Groups identical F patterns.
    ``fac``: the factor of the (one) free block, already made and counted."""
    if len(cols) == 0:
        return
    for group in _free_groups(F, cols).values():
        idx = np.flatnonzero(F[:, group[0]])
        X[:, group] = 0.0
        if idx.size == 0:
            G[:, group] = -B[:, group]
            continue
        # the block factorised in place; the refinement's residual and the gradient from products with Q
        f = fac
        if f is None:
            f = _Factor(_free_block(Q, idx), remake=lambda: _free_block(Q, idx))
            stats.factorizations += 1
            stats.max_jitter = max(stats.max_jitter, f.jitter)
        stats.largest_block = max(stats.largest_block, idx.size)
        Bf = B[np.ix_(idx, group)]
        full = np.zeros((Q.shape[0], len(group)))

        def residual(xs: np.ndarray) -> np.ndarray:
            full[idx] = xs
            return Bf - (Q @ full)[idx]

        xs = f.solve(Bf, refine=1, residual=residual)
        X[np.ix_(idx, group)] = xs
        full[idx] = xs
        G[:, group] = Q @ full - B[:, group]


class _SchurFree:
    """Free-block solves through one Cholesky of the whole matrix: x with x_Z = 0 for a fixed (zero) set Z is
    ``Q^-1 (b + E_Z mu)`` with ``(Q^-1)_ZZ mu = -(Q^-1 b)_Z`` and the gradient ``g_Z = mu`` (g_F = 0).

    With Q = U^T U, ``(Q^-1)_ZZ = W_Z^T W_Z`` for ``W = U^-T E``; W's columns are computed once per variable
    that ever enters a zero set and cached. A pivot round then costs O(z^2 N + N^2) instead of a new Cholesky of
    the free block (O(|F|^3)): with few zeros, as in an envmap, that is what makes reweighted solves cheap.
    With ``refine`` one step of iterative refinement against Q follows each solve; without it the KKT residual
    measured on the bundled scenes was still ~1e-15 (the solve's final check reports it either way, and a
    solve that misses ``tol`` is finished by the per-block method).
    """

    def __init__(self, Q: np.ndarray, B: np.ndarray, stats: _Stats, refine: bool = False):
        self.Q, self.B, self.refine, self.stats = Q, B, refine, stats
        self.fac = None  # factorised on first use: a solve that falls back to blocks never pays for it

    def _ensure(self) -> None:
        if self.fac is not None:
            return
        Q, stats = self.Q, self.stats
        self.fac = _Factor(Q)
        stats.factorizations += 1
        stats.max_jitter = max(stats.max_jitter, self.fac.jitter)
        stats.largest_block = max(stats.largest_block, Q.shape[0])
        self.X0 = self.fac.solve(self.B, refine=1 if self.refine else 0)  # (N, C) unconstrained solutions
        self.W = np.empty(Q.shape, order="F")  # columns filled on demand (``have``); never read unfilled
        self.have = np.zeros(Q.shape[0], dtype=bool)

    def _w(self, Z: np.ndarray) -> np.ndarray:
        new = Z[~self.have[Z]]
        if new.size:
            E = np.zeros((self.Q.shape[0], new.size))
            E[new, np.arange(new.size)] = 1.0
            self.W[:, new] = nogil.trtrs(self.fac.c, E, trans=True)
            self.have[new] = True
        return self.W[:, Z]

    def _constrained(self, X0: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """Q^-1 (r + E_Z mu) for the columns of X0 = Q^-1 r, with mu making x_Z = 0."""
        if Z.size == 0:
            return X0.copy()
        Wz = self._w(Z)
        S = Wz.T @ Wz
        mu = -nogil.cho_solve(nogil.cho_factor(S), X0[Z])
        X = X0 + nogil.trtrs(self.fac.c, Wz @ mu)
        X[Z] = 0.0
        return X

    def __call__(self, F: np.ndarray, cols, X: np.ndarray, G: np.ndarray) -> None:
        if len(cols) == 0:
            return
        self._ensure()
        for group in _free_groups(F, cols).values():
            Z = np.flatnonzero(~F[:, group[0]])
            Bg = self.B[:, group]
            Xg = self._constrained(self.X0[:, group], Z)
            Gg = self.Q @ Xg - Bg
            if self.refine:  # solve again for the residual on the free set
                R = -Gg
                R[Z] = 0.0
                Xg = Xg + self._constrained(self.fac.solve(R, refine=0), Z)
                Gg = self.Q @ Xg - Bg
            X[:, group] = Xg
            G[:, group] = Gg


#: fewest unknowns for which the reweighted solves (objcam.solvers.edges) pass ``split`` and use PCG free blocks:
#: at 32 x 64 (804 unknowns) the Cholesky path took 0.04-0.06 CPU s per solve against 0.07-0.13 by PCG, at
#: 64 x 128 (3,131) 1.1-3.4 s against 0.3-0.8 s (bench/results.md, issue 26 session 18)
PCG_MIN_UNKNOWNS = 1024
#: fewest free variables for which a free block is solved by PCG (below it a Cholesky of the block is cheap;
#: not tuned: the bench's blocks at 64 x 128 are 1,000-2,700)
PCG_MIN_BLOCK = 256
#: PCG stops when every free gradient entry is below this fraction of the pivoting's tolerance tg (so the
#: pivoting's sign tests see the block's exact solution), and gives the block to Cholesky after PCG_MAX_IT
PCG_SLACK = 1e-2
#: the rounds before the pivoting's last stop PCG at this multiple of tg: their free sets are guesses that the
#: next exchange corrects, so a rough solution serves (a round that finds nothing infeasible is redone to
#: PCG_SLACK and checked again: the answer is the same). A solve at a looser tol than DEFAULT_TOL (the edge
#: steps' STEP_TOL) keeps the default's loose scale: at 1e4 x its own tg the guesses took more rounds
PCG_LOOSE = 1e4
PCG_MAX_IT = 60
#: a free set whose difference from a base's is at most this many times the preconditioner's rank k is served
#: by a bordered update of that base (:class:`_Bordered`) instead of a fresh set-up
PCG_UPDATE_RANKS = 1.0


#: fresh preconditioner set-ups kept per solve as bases for bordered updates (the newest first)
_MAX_BASES = 8


class _Base:
    """A fresh preconditioner set-up on the free set ``idx`` (|F0|,): ``apply(R) = P_F0F0^-1 R`` for R (|F0|, m),
    P = M + V diag(lam) V^T, M sparse (S + diag(c)): Woodbury with a sparse LU of M_F0F0 and a Cholesky of the
    k x k capacitance (M CSR, symmetric). ``mask`` (N,) bool: F0; ``pos`` (N,): a variable's row in F0, -1
    outside it."""

    def __init__(self, idx: np.ndarray, mask: np.ndarray, M, V: np.ndarray, lam: np.ndarray):
        from scipy.sparse.linalg import splu

        self.idx, self.mask = idx, mask
        self.pos = np.full(mask.size, -1)
        self.pos[idx] = np.arange(idx.size)
        # M is CSR and symmetric: the block's rows, and its transpose as the CSC matrix splu takes (no conversion)
        self.lu = splu(M[idx][:, idx].T, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
        self.Y = self.cap = None
        if lam.size:
            Vf = V[idx]
            self.Y = self.lu.solve(Vf)  # M_FF^-1 V_F, (|F0|, k)
            self.cap = nogil.cho_factor(np.diag(1.0 / lam) + Vf.T @ self.Y)

    def apply(self, R: np.ndarray) -> np.ndarray:
        Z = self.lu.solve(R)
        if self.Y is not None:
            Z -= self.Y @ nogil.cho_solve(self.cap, self.Y.T @ R)
        return Z


class _Bordered:
    """P_FF^-1 for a free set F near a base's F0, from the base's factors (exact up to rounding, so PCG takes the
    iterations of a fresh set-up): with H = P_F0F0^-1, F' = F0 minus the removed set R and A = F minus F0,

    * removing R: ``P_F'F'^-1 = H_F'F' - H_F'R (H_RR)^-1 H_RF'`` (H's columns on R: |R| base applications);
    * adding A: block elimination with ``K = P_F'F'^-1 P_F'A`` and the Schur complement ``T = P_AA - P_AF' K``.

    Set-up ~(|R| + |A|) base applications (against a sparse LU and k of them), each application one base
    application and a few |F| x (|R| + |A|) products."""

    def __init__(self, base: _Base, idx: np.ndarray, mask: np.ndarray, M, V: np.ndarray, lam: np.ndarray):
        self.base = base
        inb = base.mask[idx]
        self.keep = np.flatnonzero(inb)  # rows of F in F0 (F' in F's order)
        self.add = np.flatnonzero(~inb)  # rows of F outside F0 (A)
        self.pk = base.pos[idx[self.keep]]  # their rows in F0
        rem = np.flatnonzero(base.mask & ~mask)
        self.pr = base.pos[rem]  # rows of F0 that left F
        self.n0 = base.idx.size
        self.WR = None
        if rem.size:
            E = np.zeros((self.n0, rem.size))
            E[self.pr, np.arange(rem.size)] = 1.0
            self.WR = base.apply(E)  # H's columns on R, (|F0|, |R|)
            self.HRR = nogil.cho_factor(0.5 * (self.WR[self.pr] + self.WR[self.pr].T))
        self.K = None
        if self.add.size:
            fa, fk = idx[self.add], idx[self.keep]
            Va = V[fa] * lam
            Ma = M[fa]  # (the rows of A: M is CSR and symmetric)
            B = Ma[:, fk].toarray().T + V[fk] @ Va.T  # P_F'A
            self.K = self._inner(B)
            T = Ma[:, fa].toarray() + V[fa] @ Va.T - B.T @ self.K
            self.B, self.T = B, nogil.cho_factor(0.5 * (T + T.T))

    def _inner(self, R: np.ndarray) -> np.ndarray:
        """P_F'F'^-1 R for R (|F'|, m)."""
        U = np.zeros((self.n0, R.shape[1]))
        U[self.pk] = R
        W = self.base.apply(U)
        if self.WR is not None:
            W -= self.WR @ nogil.cho_solve(self.HRR, W[self.pr])
        return W[self.pk]

    def __call__(self, R: np.ndarray) -> np.ndarray:
        Z = np.empty_like(R)
        z = self._inner(R[self.keep])
        if self.K is not None:
            za = nogil.cho_solve(self.T, R[self.add] - self.B.T @ z)
            z -= self.K @ za
            Z[self.add] = za
        Z[self.keep] = z
        return Z


class _PCGFree:
    """Free-block solves by preconditioned conjugate gradients for ``Q = G + S`` (S sparse, G dense PSD with
    ``G >= V diag(lam) V^T``, objcam.solvers.lowrank): the preconditioner of a free block F is
    ``P_FF = (S + diag(c) + V diag(lam) V^T)_FF``, c the diagonal of G's remainder, applied by Woodbury with a
    sparse LU of ``(S + diag(c))_FF`` (a grid stencil) and a Cholesky of the k x k capacitance matrix
    ``diag(1 / lam) + V_F^T (S + c)_FF^-1 V_F``. Products with Q are dense (N^2 per column and iteration).

    Each block is warm-started from the round's previous x and solved until every free gradient entry is below
    PCG_SLACK tg; a block PCG does not finish in PCG_MAX_IT iterations (or a free set below PCG_MIN_BLOCK) is
    solved by Cholesky (:func:`_solve_free`), counted in ``stats``. Cost per block: one sparse LU, k sparse
    solves and |F| k^2 for the capacitance (a fresh set-up, :class:`_Base`), or, for a free set within
    PCG_UPDATE_RANKS k variables of a set-up of the same solve, ~(|R| + |A|) applications of that set-up
    (:class:`_Bordered`: the same operator); then ~2 |F| N per iteration (:func:`objcam.solvers.products.sym_dot`), against |F|^3 / 3 for
    its Cholesky. On the 14 exact solves of a 64 x 128 forest run the updates served 152 of 222 preconditioners
    (the same 232 CG iterations) and the solves took 4.6-5.7 CPU s against 6.7-7.6 (bench/results.md, issue 26
    session 19).
    """

    def __init__(self, Q: np.ndarray, B: np.ndarray, S, V: np.ndarray, lam: np.ndarray, tg: np.ndarray,
                 stats: _Stats, loose_tg: np.ndarray | None = None):
        import scipy.sparse as sp

        self.Q, self.B, self.stats, self.tg = Q, B, stats, tg
        self.loose_tg = tg if loose_tg is None else loose_tg  # the loose rounds' scale (PCG_LOOSE x it)
        keep = lam > 0
        self.V, self.lam = np.ascontiguousarray(V[:, keep]), lam[keep]
        S = sp.csc_matrix(S)
        # G's diagonal beyond the low-rank part (>= 0 for a Nystrom bound): a Jacobi term for the remainder
        c = np.maximum(diagonal(Q) - S.diagonal() - (self.V * self.V) @ self.lam, 0.0)
        self.M = sp.csr_matrix(S + sp.diags(c))  # rows of a free set are taken from it: CSR
        self.first = True  # until a first call leaves X and G consistent (G = Q X - B)
        self.loose = PCG_LOOSE > PCG_SLACK  # rounds before the pivoting's last are solved to PCG_LOOSE tg
        self.rough = np.zeros(B.shape[1], dtype=bool)  # columns whose last solve was loose
        self._cols: list[int] = []
        self._precs: dict[bytes, object] = {}
        self._bases: list[_Base] = []  # this solve's fresh set-ups, newest first

    def _preconditioner(self, idx: np.ndarray):
        """z = P_FF^-1 r for r (|F|, m): Woodbury on the free rows. A free set close to one already set up in
        this solve (the previous round's, another colour column's) is served by that base's factors through a
        bordered update (:class:`_Bordered`); otherwise a fresh set-up, which becomes a base."""
        mask = np.zeros(self.Q.shape[0], dtype=bool)
        mask[idx] = True
        best, cost = None, None
        for base in self._bases:  # the base with the fewest variables to remove and add
            c = int(np.count_nonzero(mask ^ base.mask))
            if cost is None or c < cost:
                best, cost = base, c
        # an update costs ~one base application per changed variable, a set-up a sparse LU and k of them
        if best is not None and cost <= PCG_UPDATE_RANKS * max(self.lam.size, 1):
            try:
                pr = _Bordered(best, idx, mask, self.M, self.V, self.lam)
                self.stats.pcg_updates += 1
                return pr
            except np.linalg.LinAlgError:  # a numerically indefinite border: set up afresh
                pass
        base = _Base(idx, mask, self.M, self.V, self.lam)
        self.stats.pcg_setups += 1
        self._bases = [base] + self._bases[: _MAX_BASES - 1]
        return base.apply

    def _product(self, V: np.ndarray) -> np.ndarray:
        """Q V (N, m) for V (N, m): :func:`objcam.solvers.products.dot`."""
        return dot(self.Q, V)

    def _start(self, X: np.ndarray, G: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(X0, Q X0) for columns whose X (N, m), G = Q X - B (N, m) are the previous round's and F (N, m) the new
        free sets: X0 is X on F clipped at 0 and 0 off F; Q X0 is updated from Q X = G + B through the few rows
        that changed (the variables that left F, and the clipped ones) instead of a full product."""
        X0 = np.where(F, np.maximum(X, 0.0), 0.0)
        QX = G + self.B[:, self._cols]
        moved = np.flatnonzero(np.any(X0 != X, axis=1))
        if moved.size > self.Q.shape[0] // 4:
            return X0, self._product(X0)
        if moved.size:
            QX = QX + self.Q.take(moved, axis=0).T @ (X0[moved] - X[moved])
        return X0, QX

    def _pcg(self, blocks: list[tuple[bytes, np.ndarray, list[int]]], X0: np.ndarray, QX: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """PCG on every ``(key, idx, group)`` block's ``Q_FF x_F = b_F`` (key: :func:`_free_groups`'s) at once
        from X0 (N, m; 0 off F) with QX = Q X0: one product of Q with all the columns' directions per iteration.
        Returns (X, Q X (N, m), accumulated over the iterations, done (m,) bool) for the m = sum |group| columns
        in order."""
        cols = self._cols
        spans, j = [], 0
        for _, idx, group in blocks:
            spans.append((idx, slice(j, j + len(group))))
            j += len(group)
        lim = PCG_LOOSE * self.loose_tg[cols] if self.loose else PCG_SLACK * self.tg[cols]  # (m,)
        mask = np.zeros(X0.shape, dtype=bool)
        for idx, sl in spans:
            mask[idx, sl] = True
        # a block's preconditioner is kept for the next call (the tightening re-solve of the same free set)
        precs = [self._precs.get(key) or self._preconditioner(idx) for key, idx, _ in blocks]
        self._precs = {key: pr for (key, _, _), pr in zip(blocks, precs)}
        Xn, QX = X0.copy(), QX.copy()
        R = np.where(mask, self.B[:, cols] - QX, 0.0)  # the residual on each column's free rows, 0 off them

        def prec(R: np.ndarray) -> np.ndarray:
            Z = np.zeros_like(R)
            for (idx, sl), pr in zip(spans, precs):
                Z[idx, sl] = pr(R[idx, sl])
            return Z

        Z = prec(R)
        Pd = Z
        rz = np.einsum("ij,ij->j", R, Z)
        live = np.ones(len(cols), dtype=bool)
        for _ in range(PCG_MAX_IT):
            live &= np.max(np.abs(R), axis=0) > lim
            if not live.any():
                break
            self.stats.cg_iterations += 1
            L = np.flatnonzero(live)
            QP = self._product(Pd[:, L])
            Ap = np.where(mask[:, L], QP, 0.0)
            pap = np.einsum("ij,ij->j", Pd[:, L], Ap)
            alpha = np.where(pap > 0, rz[L] / np.where(pap > 0, pap, 1.0), 0.0)
            Xn[:, L] += Pd[:, L] * alpha
            QX[:, L] += QP * alpha
            R[:, L] -= Ap * alpha
            Z = prec(R)
            rzn = np.einsum("ij,ij->j", R, Z)
            beta = np.where(rz > 0, rzn / np.where(rz > 0, rz, 1.0), 0.0)
            Pd = Z + Pd * beta
            rz = rzn
        done = ~live | (np.max(np.abs(R), axis=0) <= lim)
        return Xn, QX, done

    def tighten(self, F: np.ndarray, cols, X: np.ndarray, G: np.ndarray) -> bool:
        """Re-solve to PCG_SLACK tg the columns among ``cols`` whose last solve was loose (warm: a few
        iterations); True when there were any (the pivoting then checks them again)."""
        redo = [int(c) for c in cols if self.rough[c]]
        if not redo:
            return False
        self.loose = False
        self(F, redo, X, G)
        self.loose = True
        self.stats.pcg_tightened += len(redo)
        return True

    def __call__(self, F: np.ndarray, cols, X: np.ndarray, G: np.ndarray) -> None:
        if len(cols) == 0:
            return
        blocks, small = [], []
        for key, group in _free_groups(F, cols).items():
            idx = np.flatnonzero(F[:, group[0]])
            (blocks if idx.size >= PCG_MIN_BLOCK else small).append((key, idx, group))
        for _, _, group in small:  # small free blocks: a Cholesky each is cheaper
            _solve_free(self.Q, self.B, F, group, X, G, self.stats)
            self.rough[group] = False
        if not blocks:
            self.first = False
            return
        self.stats.pcg_blocks += len(blocks)
        self._cols = allc = [c for _, _, group in blocks for c in group]
        Fm = F[:, allc]
        if self.first:  # X and G are not yet a consistent pair: one full product
            X0 = np.where(Fm, np.maximum(X[:, allc], 0.0), 0.0)
            QX = self._product(X0)
        else:
            X0, QX = self._start(X[:, allc], G[:, allc], Fm)
        try:
            Xn, QX, done = self._pcg(blocks, X0, QX)
        except (RuntimeError, np.linalg.LinAlgError):  # a singular (S + c)_FF or capacitance: Cholesky blocks
            self.stats.pcg_fallbacks += len(allc)
            _solve_free(self.Q, self.B, F, allc, X, G, self.stats)
            self.rough[allc] = False
            self.first = False
            return
        self.first = False
        self.rough[allc] = self.loose
        X[:, allc] = Xn
        G[:, allc] = QX - self.B[:, allc]
        if not done.all():  # PCG stalled on these columns: their blocks by Cholesky
            bad = [c for c, o in zip(allc, done) if not o]
            self.stats.pcg_fallbacks += len(bad)
            _solve_free(self.Q, self.B, F, bad, X, G, self.stats)
            self.rough[bad] = False


def _pivot(Q, B, F, X, G, tg, tx, cols, max_iter, stats: _Stats, free=None) -> tuple[int, bool]:
    """Block principal pivoting on columns ``cols`` (F, X, G already consistent). Returns (steps, converged).
    ``free(F, cols, X, G)`` solves the free blocks (default: a Cholesky of each distinct free block)."""
    cols = np.asarray(cols)
    ninf = np.full(cols.size, F.shape[0] + 1)
    retries = np.full(cols.size, 3)
    steps = 0
    while True:
        Fc, Xc, Gc = F[:, cols], X[:, cols], G[:, cols]
        V = (Fc & (Xc < -tx[:, cols])) | (~Fc & (Gc < -tg[cols]))
        nv = V.sum(axis=0)
        todo = np.flatnonzero(nv > 0)
        if todo.size == 0:
            if getattr(free, "tighten", None) is not None and free.tighten(F, cols, X, G):
                continue  # the free blocks were solved loosely: check their exact solutions
            return steps, True
        if steps >= max_iter:
            return steps, False
        for j in todo:
            c = cols[j]
            if nv[j] < ninf[j]:  # progress: exchange all infeasible variables
                ninf[j] = nv[j]
                retries[j] = 3
                F[V[:, j], c] ^= True
            elif retries[j] >= 1:  # no progress: exchange all, a limited number of times
                retries[j] -= 1
                F[V[:, j], c] ^= True
            else:  # Murty's rule: exchange only the last infeasible variable
                F[np.flatnonzero(V[:, j])[-1], c] ^= True
        if free is None:
            _solve_free(Q, B, F, cols[todo], X, G, stats)
        else:
            free(F, cols[todo], X, G)
        steps += 1


#: solve_exact's relative KKT tolerance (its reported residual is ~this or less)
DEFAULT_TOL = 1e-10


def solve_exact(
    Q: np.ndarray,
    B: np.ndarray,
    tol: float = DEFAULT_TOL,
    max_iter: int | None = None,
    passive0: np.ndarray | None = None,
    schur: bool | None = None,
    coarse=None,
    split: tuple | None = None,
    x0: np.ndarray | None = None,
) -> SolveResult:
    """Exact minimiser of ``0.5 x^T Q x - b^T x`` over ``x >= 0`` for every column of ``B``.

    Q: (N, N) symmetric positive semi-definite float64 (e.g. ``A^T A + ls D^T D + lr I``).
    B: (N,) or (N, C) float64 right-hand sides (``A^T y`` per channel / target).
    tol: relative optimality tolerance; a variable counts as infeasible when ``g_i < -tol * max|b|`` (outside
        the free set) or ``x_i < -tol * max|b| / sqrt(Q_ii max_j Q_jj)`` (inside it, so that clipping it to 0
        moves no gradient entry by more than tol * max|b|). The reported KKT residual is ~tol or less.
    max_iter: limit on pivoting steps (default ``10 * N + 100``); on reaching it the result has
        ``converged=False`` and its true KKT residual.
    passive0: optional (N,) or (N, C) bool initial free set (e.g. from a previous solve); default all-free, i.e.
        the first step is the unconstrained solution.
    schur: solve the free blocks through one Cholesky of the whole Q and Schur complements over the zero set
        (:class:`_SchurFree`; fast when few variables are at 0) instead of one Cholesky per free block. None:
        when N >= 256; a solve whose zero set grows past N / 3 finishes with per-block factorisations.
    coarse: optional (N, N_c) 0/1 sparse aggregation P_c (objcam.solvers.multilevel.aggregates): without
        ``passive0`` and with N >= multilevel.MIN_UNKNOWNS, the first free set is that of the exact solution on
        ``x = P_c z`` (a coarse-to-fine warm start; the minimiser is the same).
    split: optional ``(S, V, lam)`` with ``Q = G + S``, S (N, N) sparse and G >= V diag(lam) V^T (V (N, k), e.g.
        objcam.solvers.lowrank.gram_lowrank of G): free blocks of >= PCG_MIN_BLOCK variables are solved by PCG
        preconditioned by ``S + V diag(lam) V^T`` (:class:`_PCGFree`) instead of Cholesky; ``schur`` is then
        ignored. The pivoting, its tolerance and the final KKT check are the same; a solve that ends above
        ``tol`` is finished from its free set with Cholesky blocks (counted in ``info["pcg_restarts"]``).
    x0: optional (N,) or (N, C) starting point for the PCG path's first free-block solves (e.g. the previous
        reweighting step's minimiser): its values on the first free set, 0 elsewhere. It changes where CG starts,
        not the minimiser; the Cholesky paths solve their blocks directly and ignore it.

    Block principal pivoting with Cholesky of the free blocks; see the module docstring. Runs with one BLAS
    thread. Returns a :class:`SolveResult` with x (N, C), the Gram-form objective ``x^T Q x - 2 b^T x`` and
    the KKT residual per column.
    """
    t0 = time.perf_counter()
    op = isinstance(Q, GramPlusSparse)  # Q = G + S unformed (with ``split``: the PCG path needs only products)
    if not op:
        Q = np.asarray(Q, dtype=np.float64)
    B2 = _as_2d(B)
    n, ncol = B2.shape
    if Q.shape != (n, n):
        raise ValueError(f"Q is {Q.shape}, B has {n} rows")
    # (a non-finite entry makes the sum non-finite: the N^2 elementwise test only when the sum is, e.g. overflowed)
    if not (Q.finite() if op else all_finite(Q)) or not np.all(np.isfinite(B2)):
        raise ValueError("Q and B must be finite")
    if max_iter is None:
        max_iter = 10 * n + 100
    stats = _Stats()

    d = diagonal(Q).copy()
    dmax = float(d.max()) if n else 0.0
    dead = d <= 1e-300 if dmax <= 0 else d <= 1e-20 * dmax
    if np.any(dead & np.any(B2 > 0, axis=1)):
        # With Q_ii = 0 (and so row i of a PSD Q zero) and b_i > 0 the objective is unbounded below.
        bad = np.flatnonzero(dead & np.any(B2 > 0, axis=1))
        raise ValueError(f"objective unbounded: Q_ii = 0 but b_i > 0 for {bad.size} variable(s), e.g. {bad[0]}")
    live = np.flatnonzero(~dead)
    t_coarse = None
    if passive0 is None and coarse is not None and n >= multilevel.MIN_UNKNOWNS:
        t_coarse = time.perf_counter()
        passive0 = multilevel.coarse_passive(Q, B2, coarse, lambda Qc, Bc: solve_exact(Qc, Bc, tol=tol))
        t_coarse = time.perf_counter() - t_coarse

    X = np.zeros((n, ncol))
    iters = 0
    converged = True
    use_schur = use_pcg = False
    restarts = 0
    QX = None
    with single_blas_thread():
        if live.size:
            Ql = Q if live.size == n else (Q.restrict(live) if op else Q[np.ix_(live, live)])
            Bl = B2[live]
            dl = d[live]
            bscale = np.max(np.abs(Bl), axis=0)
            bscale = np.where(bscale > 0, bscale, 1.0)
            tg = tol * bscale  # (C,)
            # Clipping a free x_i < 0 to 0 moves every g_j by at most sqrt(Q_jj Q_ii) |x_i|: keep that below tg.
            tx = tg[None, :] / np.sqrt(dl.max() * dl)[:, None]  # (N_live, C), units of x
            tx = np.broadcast_to(tx, (live.size, ncol))
            if passive0 is None:
                F = np.ones((live.size, ncol), dtype=bool)
            else:
                p0 = np.asarray(passive0, dtype=bool)
                p0 = p0[:, None] if p0.ndim == 1 else p0
                F = np.broadcast_to(p0, (n, ncol))[live].copy()
            Xl = np.zeros((live.size, ncol))
            if x0 is not None:
                x0 = np.asarray(x0, dtype=np.float64)
                x0 = x0[:, None] if x0.ndim == 1 else x0
                if x0.shape != (n, ncol) or not np.all(np.isfinite(x0)):
                    raise ValueError(f"x0 must be finite with shape {(n, ncol)}, got {x0.shape}")
                Xl = np.where(F, np.maximum(x0[live], 0.0), 0.0)
            Gl = np.zeros((live.size, ncol))
            allc = np.arange(ncol)
            use_pcg = split is not None and live.size >= PCG_MIN_BLOCK
            use_schur = not use_pcg and (live.size >= 256 if schur is None else bool(schur))
            if op and not use_pcg:  # the Cholesky paths factorise blocks of Q: form it
                Ql = Ql.toarray()
            if use_pcg:
                S, V, lam = split
                if live.size < n:
                    S, V = S.tocsr()[live][:, live], V[live]
                # a looser tol (the edge steps' STEP_TOL) keeps the loose rounds where the default tol puts them:
                # looser, their free sets are guesses that take more rounds (bench/results.md, issue 26)
                pcg = _PCGFree(Ql, Bl, S, V, lam, tg, stats, loose_tg=np.minimum(tg, DEFAULT_TOL * bscale))
                pcg(F, allc, Xl, Gl)
                it, converged = _pivot(Ql, Bl, F, Xl, Gl, tg, tx, allc, max_iter, stats, free=pcg)
                QX = dot(Ql, np.maximum(Xl, 0.0))  # the final check's product, kept for the KKT and objective
                if converged and float(kkt_residual(Ql, Bl, np.maximum(Xl, 0.0), QX=QX).max()) > tol:
                    # what PCG left above tol (not seen on the bench's solves): Cholesky blocks from its free set
                    restarts += 1
                    _solve_free(Ql, Bl, F, allc, Xl, Gl, stats)
                    it2, converged = _pivot(Ql, Bl, F, Xl, Gl, tg, tx, allc, max_iter, stats)
                    it += 1 + it2
                    QX = None
            elif use_schur:
                free = _SchurFree(Ql, Bl, stats)
                blocks = blockchol.UpdatedFree(
                    Ql, Bl, stats, lambda F_, g, X_, G_, fac=None: _solve_free(Ql, Bl, F_, g, X_, G_, stats, fac=fac)
                ) if blockchol.CHOL_UPDATE_SHARE > 0 else None
                limit = live.size // 3

                def guarded(F_, cols_, X_, G_):
                    # per column: many zeros make a Cholesky of its (small) free block cheaper than the Schur
                    # complement over its zero set
                    cols_ = np.asarray(cols_)
                    many = (~F_[:, cols_]).sum(axis=0) > limit
                    if many.any() and blocks is not None:
                        blocks(F_, cols_[many], X_, G_)
                    elif many.any():
                        _solve_free(Ql, Bl, F_, cols_[many], X_, G_, stats)
                    if not many.all():
                        free(F_, cols_[~many], X_, G_)

                guarded(F, allc, Xl, Gl)
                it, converged = _pivot(Ql, Bl, F, Xl, Gl, tg, tx, allc, max_iter, stats, free=guarded)
            else:
                _solve_free(Ql, Bl, F, allc, Xl, Gl, stats)
                it, converged = _pivot(Ql, Bl, F, Xl, Gl, tg, tx, allc, max_iter, stats)
            iters = 1 + it
            X[live] = np.maximum(Xl, 0.0)
        QX = QX if use_pcg and live.size == n else None
        kkt = kkt_residual(Q, B2, X, QX=QX)
        obj = objective(Q, B2, X, QX=QX)
    return SolveResult(
        x=X,
        iterations=iters,
        kkt_residual=kkt,
        objective=obj,
        seconds=time.perf_counter() - t0,
        method="exact",
        converged=converged,
        info={
            "factorizations": stats.factorizations,
            "max_jitter": stats.max_jitter,
            "largest_block": stats.largest_block,
            "schur": bool(live.size and use_schur),
            **({"chol_updates": stats.chol_updates} if use_schur else {}),
            **({"pcg_blocks": stats.pcg_blocks, "pcg_fallbacks": stats.pcg_fallbacks,
                "cg_iterations": stats.cg_iterations, "pcg_tightened": stats.pcg_tightened,
                "pcg_setups": stats.pcg_setups, "pcg_updates": stats.pcg_updates,
                "pcg_restarts": restarts} if use_pcg else {}),
            "fixed_zero_variables": int(dead.sum()),
            "active": [int(v) for v in (X <= 0).sum(axis=0)],
            **({"coarse_start_seconds": round(t_coarse, 4)} if t_coarse is not None else {}),
        },
    )
