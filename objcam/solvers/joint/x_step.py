"""The envmap (x) block step of the alternation, for fixed albedo: exact by NNLS on Gram matrices, or by PCG.

For fixed rho every x_lc solves the convex QP ``min x^T Q_lc x - 2 b_lc^T x, x >= 0`` with one Gram matrix per
channel ``G_c = sum_p A'_p^T diag(rho_pc^2) A'_p``, shared by the L targets (and by the channels while the albedo
is grey, as at the start), ``Q_lc = G_c + ls D^T W_l D + lr I`` (W_l = 1 for the quadratic prior: then one Q_c and
one factorisation serve all targets) and ``b_lc = sum_p A'_p^T (rho_pc * y_plc)``; solved by
:func:`objcam.solvers.nnls.solve_exact` (warm-started from the previous free set) in :func:`x_step`. Forming G_c
(2 M N^2 flops per channel) is the dominant cost; the Gram matrices of one albedo are cached for the sweep
(majorise-minimise x-steps, the final step).

The Gram matrices of the sweeps are formed from float32 products accumulated in float64 (``fast_gram``, ~2x
faster, entries to ~1e-7) when A' is float32; an x-step that would raise the objective is redone in float64 (by
the alternation). The last x-step is exact without a float64 Gram matrix: :func:`x_step_pcg` solves it by
:func:`objcam.solvers.joint.pcg.solve_nnls_pcg` with the exact float64 operator (two passes over A' per product)
by conjugate gradients preconditioned with the last sweep's float32 Gram matrices (formed at the final albedo),
which converge in a few products; its KKT residual is measured with the exact operator. (``xsolver="pcg"`` does
every x-step that way, with a reference Gram refreshed when the albedo has moved; memory-bound, it measured slower
than forming the Gram matrices on a loaded 2-core machine.)

The paper's variant (``exact=False``) takes one damped clipped step ``x <- max(0, x - alpha Q_c^{-1} (Q_c x - b))``
(Eq. 7) instead.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.linalg import cho_solve

from objcam.solvers.joint.context import StepContext
from objcam.solvers.joint.kernels import chol, matmul, tmatmul
from objcam.solvers.joint.pcg import solve_nnls_pcg
from objcam.solvers.joint.problem import JointProblem
from objcam.solvers.nnls import kkt_residual, solve_exact
from objcam.threads import blas_threads, parallel_map


def x_step(ctx: StepContext, rho: list[np.ndarray], X: np.ndarray, chans, warm: bool,
           fast: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact (or damped) x for the given rho and the quadratic prior in use, on channels ``chans``; returns
    (X, kkt) for all channels. One Gram matrix per channel; with per-target prior weights (edges) one
    factorisation per (target, channel), else one per channel for all its targets.

    rho: list of (M_p, C); X: (N, L, C) the current x (the warm start with ``warm``; the other channels are
    copied); fast: float32 Gram products (default ``ctx.fast_gram``). Returns X (N, L, C) and kkt (L, C) (0 for
    channels not in ``chans``). With ``ctx.use_pcg`` the step is :func:`x_step_pcg`.
    """
    if ctx.use_pcg:
        return x_step_pcg(ctx, rho, X, chans, warm)
    fast = ctx.fast_gram if fast is None else fast
    J = ctx.J
    t0 = time.perf_counter()
    X = X.copy()
    kk = np.zeros((J.L, J.C))
    B = J.rhs(rho, chans)
    per_target = J.huber_on
    groups = [[l] for l in range(J.L)] if per_target else [list(range(J.L))]
    # the channels' Gram matrices first (each a large product on every core), then the independent QPs of
    # the (target group, channel) pairs on a thread per core, each with one BLAS thread
    grams = {int(c): J.gram(rho, c, ctx.gram_cache, fast=fast) for c in chans}
    for ls_ in groups:
        J.R_dense(ls_[0])  # built (and cached) here, not by two threads at once
    # the tasks read the warm start from X; it is written only after every task has returned

    def one(task):
        c, ls_ = task
        Q = grams[c] + J.R_dense(ls_[0])
        Bc = B[:, ls_, c]
        if ctx.exact:
            p0 = X[:, ls_, c] > 0 if warm else None
            res = solve_exact(Q, Bc, tol=ctx.qp_tol, passive0=p0)
            return res.x, res.kkt_residual
        fac, _ = chol(Q)
        Xc = X[:, ls_, c]
        Xc = np.maximum(Xc - ctx.alpha * cho_solve(fac, Q @ Xc - Bc, check_finite=False), 0.0)
        return Xc, kkt_residual(Q, Bc, Xc)

    tasks = [(int(c), ls_) for c in chans for ls_ in groups]
    for (c, ls_), (xc, kc) in zip(tasks, parallel_map(one, tasks)):
        X[:, ls_, c] = xc
        kk[ls_, c] = kc
    ctx.timers["x"] += time.perf_counter() - t0
    return X, kk


def x_step_pcg(ctx: StepContext, rho: list[np.ndarray], X: np.ndarray, chans, warm: bool,
               grams: dict[int, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The exact x-step by :func:`objcam.solvers.joint.pcg.solve_nnls_pcg`: Q applied by passes over A', the
    preconditioner from ``grams`` {c: Gram (N, N)} (e.g. this albedo's float32 Grams) or the reference Grams
    (``ctx.pcg``, formed or refreshed here). Arguments and result as :func:`x_step`."""
    J, ref = ctx.J, ctx.pcg
    t0 = time.perf_counter()
    X = X.copy()
    kk = np.zeros((J.L, J.C))
    chans = [int(c) for c in chans]
    B = J.rhs(rho, chans)
    for c in chans:
        if grams is None and (c not in ref.grams or c in ref.stale):
            ref.grams[c] = J.gram(rho, c, {}, fast=True)
            ref.stale.discard(c)
            ref.refreshes += 1
    Gs = grams if grams is not None else ref.grams
    cols = [(l, c) for c in chans for l in range(J.L)]  # one column of the NNLS per (target, channel)
    precond, group = _preconditioners(J, Gs, cols)
    W = [np.stack([r[:, c] ** 2 for c in chans], axis=1) if r.shape[0] else np.zeros((0, len(chans)))
         for r in rho]  # (M_p, len(chans))
    cpos = {c: j for j, c in enumerate(chans)}
    dg = J.weighted_col_sq(W)  # (N, len(chans))
    diag_Q = np.stack([dg[:, cpos[c]] + J.R(l).diagonal() for l, c in cols], axis=1)
    apply_Q = _operator(J, W, np.array([l for l, _ in cols]), np.array([cpos[c] for _, c in cols]))
    Bm = np.stack([B[:, l, c] for l, c in cols], axis=1)
    X0 = np.stack([X[:, l, c] for l, c in cols], axis=1) if warm else np.zeros((J.n, len(cols)))
    p0 = None if warm else np.ones((J.n, len(cols)), dtype=bool)
    res = solve_nnls_pcg(apply_Q, diag_Q, precond, group, Bm, X0, passive0=p0, tol=ctx.qp_tol)
    for k, (l, c) in enumerate(cols):
        X[:, l, c] = res.x[:, k]
        kk[l, c] = res.kkt_residual[k]
    ref.applications += res.cg_iterations
    ref.rounds += res.rounds
    ref.steps += 1
    if grams is None and res.cg_iterations > ctx.cg_refresh * res.rounds:
        ref.stale.update(chans)  # the albedo moved away from the reference: new Gram at the next x-step
    ctx.timers["x"] += time.perf_counter() - t0
    return X, kk


def _preconditioners(J: JointProblem, Gs: dict[int, np.ndarray], cols: list[tuple[int, int]]):
    """The dense preconditioners ``Gram_c + R_l`` (N, N), one per channel (per (channel, target) with per-target
    prior weights), and for each column (l, c) the index of its own (K,)."""
    per_target = J.huber_on
    pkeys: dict[tuple[int, int], int] = {}
    precond, group = [], np.zeros(len(cols), dtype=np.int64)
    for k, (l, c) in enumerate(cols):
        key = (c, l if per_target else 0)
        if key not in pkeys:
            pkeys[key] = len(precond)
            precond.append(Gs[c] + J.R_dense(key[1]))
        group[k] = pkeys[key]
    return precond, group


def _operator(J: JointProblem, W: list[np.ndarray], col_l: np.ndarray, col_cj: np.ndarray):
    """``apply_Q(V, which)``: ``Q_k v_k`` for the columns ``which`` of the NNLS, by two float64 passes over A'.

    W: per camera the albedo weights rho^2 (M_p, C') of the step's channels; col_l, col_cj (K,): each column's
    target and position in W's channels."""

    def apply_Q(V, which):
        with blas_threads():  # two passes over A'
            return _apply_Q(V, which)

    def _apply_Q(V, which):
        which = np.asarray(which)
        out = np.zeros_like(V)
        for A, A64, w in zip(J.As, J.A64, W):
            if A.shape[0] == 0:
                continue
            U = A64 @ V if A64 is not None else matmul(A, V)
            U *= w[:, col_cj[which]]
            out += A64.T @ U if A64 is not None else tmatmul(A, U)
        for l in np.unique(col_l[which]):
            j = np.flatnonzero(col_l[which] == l)
            out[:, j] += J.R(int(l)) @ V[:, j]
        return out

    return apply_Q
