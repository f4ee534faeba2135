"""Exact non-negative x-steps of the joint solve without forming their Gram matrices.

The x-step of the joint solve (:mod:`objcam.solvers.joint.x_step`) solves, for every target l and colour channel c,

    min 0.5 x^T Q x - b^T x,  x >= 0,   Q = sum_p A'_p^T diag(w_pc) A'_p + R_l,   w_pc = rho_pc^2,

with R_l the (sparse) envmap prior of target l. Forming Q costs ~2 M N^2 flops per channel (the dominant cost of a
sweep), and Q changes with every albedo step. Here Q is never formed: its products come from two passes over A'
(``A'^T (w * (A' V))`` for all the columns V of one x-step at once, in float64), and a *reference* Gram matrix
``G_ref,c = sum_p A'_p^T diag(w_ref,pc) A'_p`` formed at an earlier albedo, plus the current R_l, serves as the
preconditioner ``P = G_ref,c + R_l``. The albedo moves little between sweeps, so ``P^-1 Q`` has its eigenvalues in
``[min w / w_ref, max w / w_ref]`` near 1 and preconditioned conjugate gradients (PCG) reach a relative residual of
1e-12 in a handful of passes. The caller refreshes G_ref when the iteration counts grow.

The bound x >= 0 is handled exactly by block principal pivoting (Judice & Pires; as :func:`objcam.solvers.nnls.
solve_exact`): a free set F per column, the free block ``Q_FF x_F = b_F`` solved by PCG (preconditioner: the
Cholesky factor of ``P_FF``), then every infeasible variable (x_i < 0 in F, g_i < 0 outside) changes side while
their number keeps falling (3 retries), else only the last one (Murty's rule). The free set is warm-started from
the previous x, so most x-steps need one round. The gradient and the KKT residual (:func:`objcam.solvers.nnls.
kkt_residual`: ``max_i |min(Q_ii x_i, g_i)| / max_i |b_i|``) are computed with the exact operator, so what is
reported is what was achieved.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.linalg import cho_solve

from objcam.solvers.joint.kernels import chol

__all__ = ["PCGResult", "solve_nnls_pcg"]


@dataclass
class PCGResult:
    """Result of :func:`solve_nnls_pcg`, one column k per right-hand side."""

    x: np.ndarray  # (N, K)
    kkt_residual: np.ndarray  # (K,)
    rounds: int  # pivoting rounds (1: the warm-started free set was right)
    cg_iterations: int  # operator applications in total
    factorizations: int
    converged: bool


def solve_nnls_pcg(apply_Q: Callable[[np.ndarray, np.ndarray], np.ndarray], diag_Q: np.ndarray,
                   precond: list[np.ndarray], group: np.ndarray, B: np.ndarray, X0: np.ndarray,
                   passive0: np.ndarray | None = None, tol: float = 1e-10, cg_tol: float = 1e-13,
                   max_rounds: int | None = None, max_cg: int = 300) -> PCGResult:
    """Exact ``argmin 0.5 x^T Q_k x - b_k^T x, x >= 0`` for every column k of B (N, K).

    apply_Q(V, cols): ``Q_k v_k`` for the columns ``cols`` (V (N, len(cols))); diag_Q (N, K) the diagonals;
    precond: dense SPD preconditioner matrices P_j (N, N); group (K,) the one column k uses; X0 (N, K) the start
    (its positive entries are the initial free set unless ``passive0`` is given). tol: relative optimality
    tolerance of the pivoting (as solve_exact); cg_tol: relative residual at which PCG stops.
    """
    n, K = B.shape
    X = np.maximum(np.asarray(X0, dtype=np.float64), 0.0).copy()
    F = (X > 0) if passive0 is None else np.asarray(passive0, dtype=bool).reshape(n, K).copy()
    bscale = np.max(np.abs(B), axis=0)
    bscale = np.where(bscale > 0, bscale, 1.0)
    tg = tol * bscale
    dmax = diag_Q.max(axis=0)
    tx = tg / np.sqrt(np.maximum(diag_Q, 1e-300) * dmax)
    max_rounds = 10 * n + 100 if max_rounds is None else max_rounds
    facs: dict[tuple[int, bytes], object] = {}
    nfac = 0
    cg_total = 0

    def factor(k):
        nonlocal nfac
        key = (int(group[k]), np.packbits(F[:, k]).tobytes())
        f = facs.get(key)
        if f is None:
            idx = np.flatnonzero(F[:, k])
            P = precond[int(group[k])]
            f = (idx, chol(P[np.ix_(idx, idx)])[0] if idx.size else None)
            facs[key] = f
            nfac += 1
        return f

    def solve_free(cols):
        """PCG on Q_FF x_F = b_F for the columns ``cols``, warm-started at X (x_Z = 0)."""
        nonlocal cg_total
        cols = list(cols)
        fs = {k: factor(k) for k in cols}
        for k in cols:
            X[~F[:, k], k] = 0.0
        R = np.zeros((n, len(cols)))
        AX = apply_Q(X[:, cols], cols)
        cg_total += 1
        for j, k in enumerate(cols):
            R[:, j] = np.where(F[:, k], B[:, k] - AX[:, j], 0.0)

        def prec(Rm, which):
            Z = np.zeros_like(Rm)
            for j, k in enumerate(which):
                idx, f = fs[k]
                if idx.size:
                    Z[idx, j] = cho_solve(f, Rm[idx, j], check_finite=False)
            return Z

        live = list(range(len(cols)))
        Z = prec(R, cols)
        Pd = Z.copy()
        rz = np.einsum("nk,nk->k", R, Z)
        bF = np.array([np.linalg.norm(B[F[:, k], k]) for k in cols])
        for _ in range(max_cg):
            rn = np.sqrt(np.einsum("nk,nk->k", R, R))
            live = [j for j in live if rn[j] > cg_tol * max(bF[j], 1e-300) and rz[j] > 0]
            if not live:
                break
            kc = [cols[j] for j in live]
            AP = apply_Q(Pd[:, live], kc)
            cg_total += 1
            for jj, j in enumerate(live):
                k = cols[j]
                ap = np.where(F[:, k], AP[:, jj], 0.0)
                pap = float(Pd[:, j] @ ap)
                if not pap > 0:
                    rz[j] = 0.0
                    continue
                al = rz[j] / pap
                X[:, k] += al * Pd[:, j]
                R[:, j] -= al * ap
            Zl = prec(R[:, live], kc)
            for jj, j in enumerate(live):
                if rz[j] <= 0:
                    continue
                rzn = float(R[:, j] @ Zl[:, jj])
                Pd[:, j] = Zl[:, jj] + (rzn / rz[j]) * Pd[:, j]
                rz[j] = rzn
        return

    def gradient(cols):
        return apply_Q(X[:, cols], cols) - B[:, cols]

    allc = list(range(K))
    solve_free(allc)
    G = gradient(allc)
    cg_total += 1
    ninf = np.full(K, n + 1)
    retries = np.full(K, 3)
    rounds = 1
    converged = True
    while True:
        V = (F & (X < -tx)) | (~F & (G < -tg[None, :]))
        nv = V.sum(axis=0)
        todo = np.flatnonzero(nv > 0)
        if todo.size == 0:
            break
        if rounds >= max_rounds:
            converged = False
            break
        for k in todo:
            if nv[k] < ninf[k]:
                ninf[k], retries[k] = nv[k], 3
                F[V[:, k], k] ^= True
            elif retries[k] >= 1:
                retries[k] -= 1
                F[V[:, k], k] ^= True
            else:
                F[np.flatnonzero(V[:, k])[-1], k] ^= True
        solve_free(todo)
        G[:, todo] = gradient(list(todo))
        cg_total += 1
        rounds += 1
    X = np.maximum(X, 0.0)
    G = gradient(allc)
    nat = np.abs(np.minimum(diag_Q * X, G))
    kkt = nat.max(axis=0) / bscale
    return PCGResult(X, kkt, rounds, cg_total, nfac, converged)
