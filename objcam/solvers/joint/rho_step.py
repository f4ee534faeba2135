"""The albedo (rho) block step of the alternation, for fixed envmaps.

For fixed x, with ``s_pil = (A'_p x_lc)_i``, the albedo problem is ``min rho^T H rho - 2 beta^T rho`` over the box,
``H = diag(a) + lp G^T G``, ``a_i = sum_l s_il^2``, ``beta_i = sum_l s_il y_il``. With lp = 0 it is separable:
``rho_i = clip(beta_i / a_i, rho_min, 1)``. With lp > 0 it is a sparse strictly convex box-constrained QP per
camera, solved exactly by :func:`objcam.solvers.joint.boxqp.solve_box_qp` (block principal pivoting for box
constraints with sparse LU factorisations of the free block; its KKT residual is checked). A pixel with ``a_i ~ 0``
(its predicted shading is zero in every target, so the data does not see its albedo) gets a proximal term
``delta (rho_i - rho_i^prev)^2`` with ``delta = 1e-12 max(a)``: it keeps its previous value when nothing else
determines it, and the step still cannot increase F. Pixels of known albedo are held at their value; the pixels of
a group (a surface of uniform unknown albedo) take their group's one value, the minimiser of its 1-D quadratic
over every camera (:mod:`objcam.solvers.joint.groups`), after the other pixels' step.

The paper's variant (``exact=False``) takes the damped clipped step ``rho <- clip(rho - beta H^{-1} (H rho -
beta_rhs), rho_min, 1)`` instead.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.sparse.linalg import splu

from objcam.solvers.joint.boxqp import solve_box_qp
from objcam.solvers.joint.context import StepContext
from objcam.solvers.joint.groups import group_terms, group_values, values_of


def rho_step(ctx: StepContext, rho: list[np.ndarray], S: list[np.ndarray], chans) -> list[np.ndarray]:
    """The albedo step on channels ``chans`` at the shading S (list of (M_p, L, C)); returns a new rho (list of
    (M_p, C)), the other channels copied from ``rho``."""
    J = ctx.J
    t0 = time.perf_counter()
    rho = [r.copy() for r in rho]
    systems: dict = {}  # (camera, channel) -> its albedo system (H, b), for the groups' step
    for k in range(J.P):
        if rho[k].shape[0] == 0:
            continue
        for c in chans:
            H, bt = J.rho_system(rho[k], S[k], J.Ys[k], k, c)
            fx = J.held(k)
            if ctx.exact and J.group_ids.size:
                systems[(k, c)] = (H, bt)
            if ctx.exact:
                if J.lp > 0 and fx.any():
                    # the held pixels' terms move to the right-hand side of the free pixels' box QP
                    fr = ~fx
                    Hc = H.tocsr()
                    r = rho[k][:, c].copy()
                    bf = bt[fr] - Hc[fr][:, fx] @ r[fx]
                    r[fr] = solve_box_qp(Hc[fr][:, fr], bf, J.rho_min, 1.0, x0=r[fr], tol=ctx.qp_tol).x
                elif J.lp > 0:
                    r = solve_box_qp(H, bt, J.rho_min, 1.0, x0=rho[k][:, c], tol=ctx.qp_tol).x
                else:
                    r = np.clip(bt / H.diagonal(), *J.bounds(k, c))
                    r[fx] = rho[k][fx, c]  # known: their value (bounds); in a group: updated below
            else:
                if J.lp > 0:
                    step = splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A").solve(H @ rho[k][:, c] - bt)
                else:
                    step = rho[k][:, c] - bt / H.diagonal()
                r = np.clip(rho[k][:, c] - ctx.beta * step, *J.bounds(k, c))
            rho[k][:, c] = r
    if ctx.exact and J.group_ids.size:
        _group_step(J, rho, chans, systems)
    ctx.timers["rho"] += time.perf_counter() - t0
    return rho


def _group_step(J, rho: list[np.ndarray], chans, systems: dict) -> None:
    """Each group's albedo in each channel of ``chans`` by its 1-D quadratic over every camera at the other pixels'
    new albedo (``systems``: (camera, channel) -> that camera's albedo system (H, b)); in place."""
    now = values_of(rho, J.groups)  # each group's albedo (C,), kept where no camera's data sees it
    for c in chans:
        parts: dict[int, list] = {int(g): [] for g in J.group_ids}
        for (k, cc), sysk in systems.items():
            if cc != c:
                continue
            H, bt = sysk
            for g in parts:
                sel = J.groups[k] == g
                if sel.any():
                    parts[g].append(group_terms(H, bt, rho[k][:, c], sel))
        vals = group_values({g: t for g, t in parts.items() if t}, {g: float(v[c]) for g, v in now.items()},
                            J.rho_min)
        for k in range(J.P):
            for g, v in vals.items():
                rho[k][J.groups[k] == g, c] = v
