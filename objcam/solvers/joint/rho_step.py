"""The albedo (rho) block step of the alternation, for fixed envmaps.

For fixed x, with ``s_pil = (A'_p x_lc)_i``, the albedo problem is ``min rho^T H rho - 2 beta^T rho`` over the box,
``H = diag(a) + lp G^T G``, ``a_i = sum_l s_il^2``, ``beta_i = sum_l s_il y_il``. With lp = 0 it is separable:
``rho_i = clip(beta_i / a_i, rho_min, 1)``. With lp > 0 it is a sparse strictly convex box-constrained QP per
camera, solved exactly by :func:`objcam.solvers.joint.boxqp.solve_box_qp` (block principal pivoting for box
constraints with sparse LU factorisations of the free block; its KKT residual is checked). A pixel with ``a_i ~ 0``
(its predicted shading is zero in every target, so the data does not see its albedo) gets a proximal term
``delta (rho_i - rho_i^prev)^2`` with ``delta = 1e-12 max(a)``: it keeps its previous value when nothing else
determines it, and the step still cannot increase F. Pixels of known albedo are held at their value.

The paper's variant (``exact=False``) takes the damped clipped step ``rho <- clip(rho - beta H^{-1} (H rho -
beta_rhs), rho_min, 1)`` instead.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.sparse.linalg import splu

from objcam.solvers.joint.boxqp import solve_box_qp
from objcam.solvers.joint.context import StepContext


def rho_step(ctx: StepContext, rho: list[np.ndarray], S: list[np.ndarray], chans) -> list[np.ndarray]:
    """The albedo step on channels ``chans`` at the shading S (list of (M_p, L, C)); returns a new rho (list of
    (M_p, C)), the other channels copied from ``rho``."""
    J = ctx.J
    t0 = time.perf_counter()
    rho = [r.copy() for r in rho]
    for k in range(J.P):
        if rho[k].shape[0] == 0:
            continue
        for c in chans:
            H, bt = J.rho_system(rho[k], S[k], J.Ys[k], k, c)
            fx = J.fixed[k]
            if ctx.exact:
                if J.lp > 0 and fx.any():
                    # the fixed pixels' terms move to the right-hand side of the free pixels' box QP
                    fr = ~fx
                    Hc = H.tocsr()
                    r = rho[k][:, c].copy()
                    bf = bt[fr] - Hc[fr][:, fx] @ r[fx]
                    r[fr] = solve_box_qp(Hc[fr][:, fr], bf, J.rho_min, 1.0, x0=r[fr], tol=ctx.qp_tol).x
                elif J.lp > 0:
                    r = solve_box_qp(H, bt, J.rho_min, 1.0, x0=rho[k][:, c], tol=ctx.qp_tol).x
                else:
                    r = np.clip(bt / H.diagonal(), *J.bounds(k, c))
            else:
                if J.lp > 0:
                    step = splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A").solve(H @ rho[k][:, c] - bt)
                else:
                    step = rho[k][:, c] - bt / H.diagonal()
                r = np.clip(rho[k][:, c] - ctx.beta * step, *J.bounds(k, c))
            rho[k][:, c] = r
    ctx.timers["rho"] += time.perf_counter() - t0
    return rho
