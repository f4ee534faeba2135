"""The entry point of the joint solve: :func:`solve_joint` and its :class:`JointResult`.

It checks the arguments, prepares the problem (:class:`objcam.solvers.joint.problem.JointProblem`), runs the
alternation (:class:`objcam.solvers.joint.alternation.Alternation`) and reports the result (x expanded from the
texel basis when one is given, weights, counters and timings in ``info``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from objcam.envmap import EnvGrid
from objcam.solvers.joint.alternation import Alternation
from objcam.solvers.joint.blocks import DEFAULT_RHO_MIN, CameraBlock
from objcam.solvers.joint.context import StepContext
from objcam.solvers.joint.problem import JointProblem
from objcam.solvers.regularization import DEFAULT_LR_REL, DEFAULT_LS_REL


@dataclass
class JointResult:
    """Result of :func:`solve_joint`.

    x: (N, L, C) envmap radiance per kept texel, target and channel.
    rho: list over cameras of (M_p, C) albedo in [rho_min, 1].
    objective: (C,) final objective per channel (:mod:`objcam.solvers.joint.problem`); ``objective.sum()`` is the
        total.
    history: (K+1,) total objective after the first x-step and after each sweep (non-increasing for "exact").
    history_channels: (K+1, C) the same per channel.
    step_history: total objective after every sub-step (x, rho, scale, x, ...), starting at (rho0, x = 0).
    iterations: sweeps done (the first x-step is sweep 0).
    converged: every channel met the relative-decrease tolerance within max_iter (and nothing diverged).
    diverged: the divergence guard tripped; x and rho are the best estimate seen (``message`` says which).
    message: one line on how the solve ended.
    kkt_x: (L, C) relative KKT residual of the final x for the final rho (x-subproblem,
        :func:`objcam.solvers.nnls.kkt_residual`).
    kkt_rho: (P, C) relative KKT residual of the final rho for the final x (rho-subproblem, box QP).
    scale_ambiguous: True unless some pixel is fixed: (c rho, x / c) fits the data equally; the regularisers pick c.
    scale_at_clip: (C,) whether max rho_c == 1, i.e. the clip fixed the scale of that channel.
    method: "exact" or "paper".  seconds: wall time.  info: weights and timings.
    """

    x: np.ndarray
    rho: list[np.ndarray]
    objective: np.ndarray
    history: np.ndarray
    history_channels: np.ndarray
    step_history: list[float]
    iterations: int
    converged: bool
    diverged: bool
    message: str
    kkt_x: np.ndarray
    kkt_rho: np.ndarray
    scale_ambiguous: bool
    scale_at_clip: np.ndarray
    method: str
    seconds: float
    info: dict[str, Any] = field(default_factory=dict)


def solve_joint(
    blocks: Sequence[CameraBlock | tuple],
    grid: EnvGrid,
    texel_index: np.ndarray,
    ls: float = DEFAULT_LS_REL,
    lr: float = DEFAULT_LR_REL,
    lp: float = 0.0,
    method: str = "exact",
    relative: bool = True,
    tol: float = 1e-6,
    max_iter: int = 100,
    rho_min: float = DEFAULT_RHO_MIN,
    scale_step: bool = True,
    accelerate: bool = True,
    anderson_depth: int = 5,
    fast_gram: bool = True,
    gn_rank: int = 128,
    gn_inner: int = 1,
    alpha: float = 0.5,
    beta: float = 0.5,
    diverge_factor: float = 10.0,
    qp_tol: float = 1e-10,
    prior: str = "smooth",
    edge_eps: float = 0.05,
    edge_steps: int = 2,
    rho_init: Sequence[np.ndarray] | None = None,
    xsolver: str = "gram",
    cg_refresh: int = 12,
    polish: bool = True,
    basis: sp.spmatrix | None = None,
    pinned_scale: bool = True,
) -> JointResult:
    """Jointly recover the albedo of every camera and the L envmaps (per colour channel); see
    :mod:`objcam.solvers.joint` and its modules.

    blocks: one :class:`CameraBlock` (or tuple ``(A', Y[, pixel_index, image_shape, rho0])``) per camera; all
        share the N kept texels ``texel_index`` on ``grid`` and the (L, C) layout of Y.
    ls, lr: envmap smoothness and ridge weights, relative to ``mean(diag(sum_p A'_p^T A'_p))``;
    lp: albedo smoothness weight, relative to ``mean_{pixels, channels} sum_l y^2``; ``relative=False`` takes
        all three as absolute.
    prior: "smooth" (quadratic ``ls ||D x||^2``) or "edges" (the edge-preserving Huber prior, minimised by
        majorise-minimise inside the alternation; ``edge_eps`` its threshold relative to the RMS edge,
        ``edge_steps`` the majorise-minimise x-steps per sweep, all on the sweep's Gram matrices); see
        :mod:`objcam.solvers.joint.problem`.
    method: "exact" (exact block-coordinate descent, monotone) or "paper" (damped clipped steps, ``alpha`` for x,
        ``beta`` for rho; no scale step, no acceleration).
    tol: stop when the relative decrease of the objective over one sweep is below ``tol`` (smooth prior: per
        channel; edges: of the total, which the shared edges couple); max_iter sweeps.
    rho_min: lower clip of the albedo (upper is 1).  scale_step: the exact 1-D scale minimisation (exact only).
    accelerate, anderson_depth: safeguarded Anderson acceleration of the albedo sequence (exact only; see
        :mod:`objcam.solvers.joint.accelerate`); the objective stays non-increasing.
    gn_rank: rank k of the subspace Gauss-Newton proposals (0 disables; see the same module);
        gn_inner: proposals per sweep before the x-step (1 is as good as more on the test scenes).
    fast_gram: form the Gram matrices of the sweeps from float32 products (float64 accumulation, ~2x faster,
        entries to ~1e-7) when A' is float32; a sweep whose x-step would raise the objective is redone in float64,
        and the final x-step is always float64, so the returned x is exact for the returned rho.
    diverge_factor: the divergence guard (see :mod:`objcam.solvers.joint.alternation`).
    qp_tol: tolerance of the exact x- and rho-subproblem solves.
    rho_init: optional initial albedo per camera (list of (M_p, C)), overriding the blocks' rho0.
    xsolver: how the sweeps' exact x-steps solve their QP: "gram" (default: form the sweep's Gram matrices,
        float32 products with ``fast_gram``; solve exactly by :func:`objcam.solvers.nnls.solve_exact`) or "pcg"
        (:func:`objcam.solvers.joint.x_step.x_step_pcg`: Q applied by passes over A', a reference Gram matrix per
        channel as the preconditioner, refreshed when a step needs more than ``cg_refresh`` operator applications
        per pivoting round; memory-bound, it measured slower than "gram" on a loaded 2-core machine). Either way
        the final x-step is polished by PCG against the exact float64 operator (:mod:`objcam.solvers.joint.pcg`)
        with the last sweep's float32 Gram matrices as the preconditioner, so the returned x is exact (KKT ~
        qp_tol) for the returned rho without forming float64 Gram matrices. The paper's method always forms them.
    polish: do that final exact x-step (default). ``False`` skips it for a solve whose result is only a starting
        point (the solve stage's first solve before a bounce refit): x is then the last sweep's x-step on float32
        Gram matrices (``kkt_x`` says how exact).
    pinned_scale: with pixels of known albedo (exact only), end with the scale they pin chosen by the data alone
        (:func:`objcam.solvers.joint.scale_step.pinned_scale`; the priors would shrink it), before the final x-step;
        ``info["pinned_scale"]``: the factors per channel and the objective before and after (F may rise: the
        histories end before it). ``False``: the minimiser of F, scale and all.
    basis: optional (N, N') 0/1 matrix P of texel groups (:func:`objcam.solvers.basis.texel_basis`): the solve
        runs on z with x = P z (A' P, the priors of the fine x: ``D P`` and the ridge ``||P z||^2``; the weights
        stay relative to the fine A'), and returns x = P z; ``kkt_x`` is the merged problem's.

    Raises :class:`NoValidPixelsError` (a ValueError) when no camera has a valid pixel. Runs with one BLAS thread.
    """
    if method not in ("exact", "paper"):
        raise ValueError(f"method must be 'exact' or 'paper', got {method!r}")
    if method == "paper" and not (alpha > 0 and beta > 0):
        raise ValueError("alpha and beta must be > 0")
    if edge_steps < 1:
        raise ValueError("edge_steps must be >= 1")
    if xsolver not in ("pcg", "gram"):
        raise ValueError(f"xsolver must be 'pcg' or 'gram', got {xsolver!r}")
    t_start = time.perf_counter()
    J = JointProblem(blocks, grid, texel_index, ls, lr, lp, relative, rho_min, prior=prior, edge_eps=edge_eps,
                     basis=basis)
    exact = method == "exact"
    if J.group_ids.size and not exact:
        raise ValueError("albedo groups (uniform surfaces) need method='exact'")
    ctx = StepContext(J, exact=exact, alpha=alpha, beta=beta, qp_tol=qp_tol, fast_gram=fast_gram,
                      use_pcg=exact and xsolver == "pcg", cg_refresh=cg_refresh)
    run = Alternation(ctx, tol=tol, max_iter=max_iter, scale_step=scale_step, accelerate=accelerate,
                      anderson_depth=anderson_depth, gn_rank=gn_rank, gn_inner=gn_inner,
                      diverge_factor=diverge_factor, edge_steps=edge_steps, polish=polish, pinned=pinned_scale)
    run.run(rho_init)
    X, timers, stats, ref = run.X, ctx.timers, run.stats, ctx.pcg
    hist_arr = np.array(run.hist)
    above = float(np.mean(J.edge_norms(X) > J.edge_thr[:, None])) if J.huber_on else 0.0
    if J.basis is not None:
        X = (J.basis @ X.reshape(J.n, -1)).reshape(-1, J.L, J.C)
    return JointResult(
        x=X,
        rho=run.rho,
        objective=run.obj_t,
        history=hist_arr.sum(axis=1),
        history_channels=hist_arr,
        step_history=run.step_hist,
        iterations=run.iters,
        converged=run.converged,
        diverged=run.diverged,
        message=run.message,
        kkt_x=run.kkt_x,
        kkt_rho=run.kkt_rho,
        scale_ambiguous=not J.any_fixed,
        scale_at_clip=run.rmax >= 1.0 - 1e-12,
        method=method,
        seconds=time.perf_counter() - t_start,
        info=dict(
            ls_abs=J.ls, lr_abs=J.lr, lp_abs=J.lp, **J.rel,
            data_scale=J.s_data, albedo_data_scale=J.t_data,
            gram_seconds=J.t_gram, grams=J.grams, x_step_seconds=timers["x"], rho_step_seconds=timers["rho"],
            anderson_accepted=stats["accepted"], anderson_rejected=stats["rejected"],
            float64_redo=stats["float64_redo"], gn_accepted=stats["gn_accepted"], gn_rejected=stats["gn_rejected"],
            gn_seconds=timers["gn"], gn_rank=0 if run.gn is None else run.gn.k, scale_seconds=timers["scale"],
            xsolver=xsolver if exact else "gram", x_steps=ref.steps, reference_grams=ref.refreshes,
            operator_applications=ref.applications, pivot_rounds=ref.rounds,
            prior=prior if J.huber_on or prior == "smooth" else "smooth (edges: no edge scale)",
            edge_scale=J.edge_s.tolist(), edge_eps=J.edge_eps_rel, mm_steps=stats["mm_steps"],
            edges_above_threshold=above, pinned_scale=run.pinned_info,
        ),
    )
