"""Edge-preserving smoothness: a Huber (smoothed total-variation) prior on the envmap's differences, minimised
exactly by majorise-minimise (iteratively reweighted quadratic solves).

Real environment maps are piecewise smooth: sky against tree line, a window against the wall. The quadratic
prior ``ls ||D x||^2`` charges an edge by its squared height, so it blurs every edge the data cannot pin down.
The Huber penalty grows linearly beyond a small threshold and keeps them. Measured on the bundled HDRIs
(bench/results.md): tonemapped SSIM of forest 0.78 -> 0.86 and courtyard 0.58 -> 0.85 with an exact A and 0.1%
noise; 0.55 -> 0.63 and 0.39 -> 0.59 on the 2048-spp path-traced targets.

Objective, for X (N, C) (C colour channels sharing the edges; grey A_c = A for every c, or one A_c each):

    F(X) = sum_c ||A_c x_c - y_c||^2 + lr sum_c ||x_c||^2 + ls * s * 2 C sum_e huber_eps(r_e),   X >= 0,
    r_e = sqrt(mean_c (D x_c)_e^2),   huber_eps(r) = r^2 / (2 eps) (r <= eps), r - eps / 2 (r > eps).

``s`` is the RMS edge height of the quadratic solution (fixed after the first solve, so F is one fixed function)
and ``eps = eps_rel * s``. Near r = s the penalty equals the quadratic prior ``ls r^2`` of the same ``ls``, so
the weights keep their meaning. Each step replaces huber by its quadratic majoriser at the current r, i.e. the
quadratic prior with per-edge weights ``w_e = s / max(r_e, eps)`` (shared by the channels), and solves that
bound-constrained quadratic exactly (:func:`objcam.solvers.nnls.solve_exact`, warm-started): F never increases.

Tone weighting (``tone = p > 0``). Real envmaps span 1e3-1e5:1, and what a person sees of one (and the tonemapped
SSIM of objcam.metrics, gamma 1/2.2) is its structure in tonemapped units: a step of 0.01 in a dark wall is as
visible as a step of 1 next to the sun. A prior in linear radiance charges the bright edges most and leaves the
dark regions, where a diffuse occluder's data are weakest relative to the noise, to wander. With ``tone`` each
edge's Huber term is weighted by

    b_e = (m / (xbar_e + delta m))^p,   normalised to mean 1,

``xbar_e`` the mean radiance of the edge's two texels (over the channels) at the current estimate, ``m`` the mean
of the estimate and ``delta = tone_floor`` (so black texels get a finite weight): ``b_e huber(r_e)`` is close to
the Huber of the differences of ``x^(1-p)``, a power law like the tonemap's. The weights follow the estimate, so
the steps are iteratively reweighted least squares for that (no longer convex) prior; each step is still the
exact bound-constrained minimiser of its quadratic majoriser, the history records F at each step's weights.
Measured on the bench's four HDRIs (bench/results.md: p 0.3, eps 0.001, ls 600 sigma^2 against p 0, eps 0.005,
300 sigma^2): SSIM courtyard 0.70 -> 0.78, sunrise 0.65 -> 0.75, forest 0.79 -> 0.79, city 0.86 -> 0.83, and
relative RMSE 0.74 -> 0.71, 4.9 -> 3.6, 0.53 -> 0.55, 1.50 -> 1.03.

The default p is the tonemap's own, 1 - 1/2.2 (objcam.solvers.plan.defaults.EDGE_TONE). Below p = 1/2 the prior
rewards spreading: a compact source of energy E over an area a costs ~E^(1-p) a^(p-1/2) in the Huber's linear part
(a square of side s: 4s edges of height E/s^2, each weighted ~(E/s^2)^-p), so at p = 0.3 an overhead lamp or a
low sun came out smeared over several texels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp

from objcam.solvers.basis import group_sizes, merge_gram
from objcam.solvers.lowrank import gram_lowrank
from objcam.solvers.multilevel import MIN_UNKNOWNS, aggregates
from objcam.solvers.nnls import PCG_MIN_UNKNOWNS, SolveResult, solve_exact
from objcam.solvers.products import GramPlusSparse, sym_dot
from objcam.solvers.regularization import regularized_gram


@dataclass
class EdgeResult:
    x: np.ndarray  # (N, C)
    results: list[SolveResult]  # the last step's exact solve per Gram block
    objective_history: list[float] = field(default_factory=list)  # F after each step (the first: quadratic solve)
    steps: int = 0
    edge_scale: float = 0.0  # s
    kept_edges: float = 0.0  # fraction of edges above eps at the end (where the prior acts like TV)
    tone: float = 0.0  # the tone exponent p used (0: none)
    # with solve_edges(keep_buffers=True): each block's (N', N') Q buffer of the last step, scratch that a solve
    # continuing from or warm-started by this result rewrites instead of allocating (a fresh 79 MB array at
    # 64 x 128 is a mapping whose pages fault in)
    buffers: list = field(default_factory=list, repr=False, compare=False)


def huber(r: np.ndarray, eps: float) -> np.ndarray:
    return np.where(r <= eps, r * r / (2 * eps), r - eps / 2)


def edge_norms(D: sp.csr_matrix, X: np.ndarray) -> np.ndarray:
    """(E,) RMS over channels of the differences ``D x_c``."""
    DX = D @ X
    return np.sqrt(np.mean(DX * DX, axis=1))


def edge_means(D: sp.csr_matrix) -> sp.csr_matrix:
    """(E, N) operator: the mean of each edge's two texels."""
    M = abs(D).tocsr()
    rs = np.asarray(M.sum(axis=1)).ravel()
    return (sp.diags(1.0 / np.where(rs > 0, rs, 1.0)) @ M).tocsr()


def tone_weights(M: sp.csr_matrix, X: np.ndarray, tone: float, floor: float) -> np.ndarray:
    """(E,) the tone weights b_e of the module docstring for the estimate X (N, C); all 1 when tone is 0."""
    if tone <= 0:
        return np.ones(M.shape[0])
    xm = M @ np.maximum(X, 0.0).mean(axis=1)
    m = float(np.mean(np.maximum(X, 0.0)))
    if m <= 0:
        return np.ones(M.shape[0])
    b = (m / (xm + floor * m)) ** tone
    return b / b.mean()


#: the KKT tolerance of the PCG path's solves before a run's last step (objcam.solvers.nnls.solve_exact's tol):
#: they only set the next step's weights, so issue 26's bar for "exact" (1e-8) serves, and the last step (or the
#: step an early stop ends on, solved again) is solved to solve_exact's default 1e-10. 64 x 128 demo: 200 -> ~175
#: CG iterations (bench/results.md, issue 26, session 24)
STEP_TOL = 1e-8

#: on the PCG path, the reweighting steps after a cold run's first start from the free set of the exact solution
#: on the coarse aggregates at the step's own weights (objcam.solvers.multilevel: a merge and a small solve) instead
#: of the previous step's free set, when the coarse problem has at most this many unknowns. The weights of steps 1
#: and 2 move much of the free set (the demo's step 1: 839 of 9,408 variables wrong from the previous step, 56
#: from the coarse problem), and each wrong variable costs pivoting rounds. Measured on 132 such solves at 64 x 128
#: (the demo and six hard-suite captures, 764-785 coarse unknowns): 31.2 s from the previous free sets, 25.5 s from
#: the coarse ones, better on 6 of 7 captures (bench/results.md, issue 26, session 26). At 128 x 256 (3,100 coarse
#: unknowns) the coarse solve costs more than it saves (24.6 -> 54.8 s, session 25): 1,500 lies between
COARSE_RESTART_MAX = 1500


def _split(G: np.ndarray, Dw: sp.spmatrix, ls: float, lr: np.ndarray) -> tuple | None:
    """``(S, V, lam)`` for objcam.solvers.nnls.solve_exact's PCG free blocks: the step's sparse part ``S = ls Dw^T
    Dw + diag(lr)`` of Q and the data Gram's low-rank bound (objcam.solvers.lowrank, once per Gram); None below
    PCG_MIN_UNKNOWNS, where Cholesky is as fast."""
    if G.shape[0] < PCG_MIN_UNKNOWNS:
        return None
    S = sp.csr_matrix(ls * (Dw.T @ Dw) + sp.diags(np.broadcast_to(lr, (G.shape[0],)).astype(float)))
    return (S, *gram_lowrank(G))


def solve_edges(grams: Sequence[np.ndarray], rhs: Sequence[np.ndarray], chans: Sequence[Sequence[int]],
                yy: np.ndarray, D: sp.csr_matrix, ls_abs: float, lr_abs: float, steps: int = 6,
                eps_rel: float = 0.05, tol: float = 1e-4,
                solve: Callable[..., SolveResult] = solve_exact, tone: float = 0.0,
                tone_floor: float = 0.05, basis: sp.spmatrix | None = None, merged: bool = False,
                start: EdgeResult | None = None, warm: EdgeResult | None = None,
                keep_buffers: bool = False, final: bool = True) -> EdgeResult:
    """Minimise F (module docstring) over X >= 0; ``tone`` > 0 weights the edges by tone (module docstring).

    grams: one data Gram matrix A_c^T A_c (N, N) per block; rhs: its (N, len(chans[b])) right-hand sides
    A_c^T y for the channels ``chans[b]`` it serves (a grey A: one block serving [0, 1, 2]).
    yy: (C,) sum of y_c^2 per channel (for the objective's value only).
    Stops after ``steps`` reweightings or when F decreases by less than ``tol`` relative.
    basis: optional (N, N') 0/1 matrix P of texel groups (objcam.solvers.basis.texel_basis): F is minimised
    over x = P z (grams, rhs and D are given on the N texels and merged here; the edge means of the tone weights
    and the ridge are those of the fine x, so F is the same function restricted to that subspace). The returned
    x is P z; ``results`` hold the merged problem's solves (their KKT residuals are in z). ``merged``: grams and
    rhs are already on the basis (``merge_gram(P, G)``, ``P^T B``): solves that share them merge them once.
    start: an earlier result of the same prior (same D, ls, eps_rel, tone, basis) on other data (the same photo
    with outlier pixels removed, objcam.solvers.outliers): the steps continue from its estimate, edge scale s and
    weights instead of a new quadratic solve, so the prior stays the same function F.
    warm: an earlier result on similar data whose free sets (x > 0) start the first exact solve (a fresh solve,
    its own edge scale, but not a cold start); ignored with ``start``.
    keep_buffers: the result holds the step's Q matrices (``buffers``) for a later solve given it as ``start``
    or ``warm``, which takes them over (else they are freed on return: one per block, N'^2 floats each).
    final: False when a later run continues from this one (``start``) after its ``steps``: its last step too only
    sets the continuation's weights and is solved to STEP_TOL on the PCG path. A run that stops early (F
    converged) is final whatever this says: its last step is then solved again to the full tolerance.
    """
    M = edge_means(D) if tone > 0 else None
    ridge_w = np.ones(D.shape[1])  # texels per unknown: the ridge of the fine x
    if basis is not None:
        P = sp.csr_matrix(basis)
        if not merged:
            grams = [merge_gram(P, G) for G in grams]
            rhs = [np.asarray(P.T @ np.asarray(B).reshape(P.shape[0], -1)) for B in rhs]
        D = sp.csr_matrix(D @ P)
        M = None if M is None else sp.csr_matrix(M @ P)
        ridge_w = group_sizes(P)
    n = D.shape[1]
    n_ch = sum(len(c) for c in chans)
    X = np.zeros((n, n_ch))
    if tone < 0 or tone_floor <= 0:
        raise ValueError("tone must be >= 0 and tone_floor > 0")
    w = np.ones(D.shape[0])
    bw = np.ones(D.shape[0])  # tone weights b_e
    results: list[SolveResult] = []
    passive: list[np.ndarray | None] = [None] * len(grams)
    history: list[float] = []
    s = eps = 0.0
    first = 0
    if warm is not None and start is None:
        z = np.asarray(warm.x if basis is None else (P.T @ warm.x) / ridge_w[:, None])
        passive = [z[:, list(ch)] > 0 for ch in chans]
    if start is not None and start.edge_scale > 0:
        X = np.asarray(start.x if basis is None else (P.T @ start.x) / ridge_w[:, None], dtype=np.float64)
        s, eps, first = start.edge_scale, eps_rel * start.edge_scale, 1
        passive = [X[:, list(ch)] > 0 for ch in chans]
        if tone > 0:
            bw = tone_weights(M, X, tone, tone_floor)
        w = bw * s / np.maximum(edge_norms(D, X), eps)
    # the first (cold) solves start from the coarse problem's free set (objcam.solvers.multilevel); a run that
    # continues or is warm-started has its free sets and never uses it
    cold = any(p is None for p in passive)
    coarse = aggregates(D) if cold and solve is solve_exact and n >= MIN_UNKNOWNS else None
    restart = coarse is not None and coarse.shape[1] <= COARSE_RESTART_MAX  # (PCG path, steps after the first)

    def objective(X: np.ndarray, solved: Sequence | None = None) -> float:
        """F(X); ``solved``: per block, None or the (result, S) of the exact solve that gave X's columns on
        ``Q = G + S``: its data term is then the solve's objective minus x^T S x (S sparse), not a product with G"""
        data = 0.0
        for b, (G, B, ch) in enumerate(zip(grams, rhs, chans)):
            Xc = X[:, list(ch)]
            if solved is not None and solved[b] is not None:
                res, S = solved[b]
                data += float(np.sum(res.objective)) - float(np.sum(Xc * (S @ Xc)))
                continue
            # G symmetric: the row-major product reading only the rows where x is nonzero (objcam.solvers.products.sym_dot)
            data += float(np.sum(Xc * sym_dot(G, Xc)) - 2 * np.sum(B * Xc))
        prior = ls_abs * s * 2 * n_ch * float((bw * huber(edge_norms(D, X), eps)).sum()) if eps > 0 else 0.0
        return data + float(yy.sum()) + lr_abs * float(np.einsum("n,nc,nc->", ridge_w, X, X)) + prior

    Qs: list[np.ndarray | None] = [None] * len(grams)  # each block's Q, rewritten in place at every step
    donor = start if start is not None else warm
    if donor is not None and len(donor.buffers) == len(grams):
        Qs = [q if q is not None and q.shape == (n, n) else None for q in donor.buffers]
        donor.buffers = []  # (handed over: the donor's last Q is overwritten by the first step here)
    loose: list[tuple | None] = [None] * len(grams)  # a block whose last solve stopped at STEP_TOL: (Q, split)
    early = False  # F converged (or the solution is flat) before ``steps``: this run is final
    for step in range(first, steps + 1):
        Dw = sp.diags(np.sqrt(w)) @ D
        results = []
        solved: list = [None] * len(grams)  # (result, S) of the PCG path's solves, for the objective
        for b, (G, B, ch) in enumerate(zip(grams, rhs, chans)):
            split = _split(G, Dw, ls_abs, lr_abs * ridge_w) if solve is solve_exact else None
            if split is not None:
                # the PCG free blocks need only products with Q = G + S: it is not formed (no N x N copy of G
                # per step; objcam.solvers.products.GramPlusSparse)
                Qs[b] = None
                op = GramPlusSparse(G, split[0])
                # a step that is not the last only sets the next step's weights: solved to STEP_TOL
                kw = {} if step == steps and final else {"tol": STEP_TOL}
                # CG starts from the previous step's minimiser (close: the weights change little between steps)
                x0 = X[:, list(ch)] if passive[b] is not None else None
                res = solve(op, B, passive0=None if restart and step > 0 else passive[b], coarse=coarse, split=split,
                            x0=x0, **kw)
                loose[b] = (op, split) if kw else None
                solved[b] = (res, split[0])
            else:
                Q = Qs[b] = regularized_gram(G, Dw, ls_abs, lr_abs * ridge_w, out=Qs[b])
                res = solve(Q, B, passive0=passive[b], coarse=coarse) if solve is solve_exact else solve(Q, B)
            X[:, list(ch)] = res.x.reshape(n, -1)
            passive[b] = res.x.reshape(n, -1) > 0
            results.append(res)
        r = edge_norms(D, X)
        if step == 0:
            s = float(np.sqrt(np.mean(r * r)))
            if s <= 0:  # a flat solution: nothing to reweight
                history.append(objective(X, solved))
                early = True
                break
            eps = eps_rel * s
        history.append(objective(X, solved))
        if len(history) > 2 - first and abs(history[-2] - history[-1]) <= tol * abs(history[-2]):
            early = step < steps
            break
        if tone > 0:
            bw = tone_weights(M, X, tone, tone_floor)
        w = bw * s / np.maximum(r, eps)
    if (final or early) and any(v is not None for v in loose):
        # a final run whose last solves stopped at STEP_TOL (it stopped early): they are finished to the full tol
        for b, (B, ch) in enumerate(zip(rhs, chans)):
            if loose[b] is not None:
                op, split = loose[b]
                res = solve(op, B, passive0=passive[b], split=split, x0=X[:, list(ch)])
                X[:, list(ch)] = res.x.reshape(n, -1)
                passive[b] = res.x.reshape(n, -1) > 0
                results[b] = res
                solved[b] = (res, split[0])
        history[-1] = objective(X, solved)
    kept = float(np.mean(edge_norms(D, X) > eps)) if eps > 0 else 0.0
    if basis is not None:
        X = np.asarray(P @ X)
    return EdgeResult(X, results, history, len(history) - 1 + first, s, kept, float(tone),
                      buffers=Qs if keep_buffers else [])
