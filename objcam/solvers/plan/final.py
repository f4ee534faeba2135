"""Unknown albedo, the final step (``final_envmap=known``): after the joint solve, rounds of the albedo's exact
step with a total-variation prior (objcam.solvers.albedo_tv: a free per-pixel albedo absorbs what the envmap
estimate gets wrong as faint shadows, which a print's piecewise-constant albedo does not have) and every envmap at
that albedo, held fixed, by the known-albedo solver (tone-weighted edges, ls from the noise)."""

from __future__ import annotations

import numpy as np

from objcam import solvers
from objcam.envmap import EnvGrid
from objcam.solvers.albedo_tv import tv_albedo
from objcam.solvers.basis import texel_basis
from objcam.solvers.edges import solve_edges
from objcam.solvers.joint import weighted_gram
from objcam.solvers.plan.defaults import EDGE_EPS_KNOWN, FINAL_EARLY_STEPS
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.rules import noise_ls, texel_group
from objcam.threads import parallel_map, single_blas_thread


def final_step(scene, data, cams: list[dict], res, grid: EnvGrid, texel_index: np.ndarray, params: SolveParams,
               ls_rule: float | None, tv: bool):
    """After the joint solve: ``final_rounds`` rounds of the albedo's edge-preserving step at the current envmaps
    (objcam.solvers.albedo_tv, when ``tv`` and ``albedo_tv`` > 0: the exact albedo step with a TV prior; lp = 0
    only, where the joint solve's albedo is each pixel's least squares) and every envmap at that albedo by the
    known-albedo solver (:func:`final_envmaps`). Without the TV step, one round at the joint solve's albedo.
    Returns (X (N, L, 3), rho (list per camera of (M_p, 3)), info for solve.json)."""
    tv = tv and params.albedo_tv > 0
    if ls_rule is not None:
        ls, source = ls_rule, f"auto_reg {params.auto_reg}"
    elif params.ls is not None:
        ls, source = params.ls, "param"
    else:  # the known-albedo rule, the median over the problem's targets
        got = [noise_ls(scene.target(t), data[t].pooled, data[t].pooled_ok, params, c["tr"].downsample, linear=True)
               for c in cams for t in c["targets"]]
        ls, source = float(np.median([g[0] for g in got])), f"median over the targets of {got[0][1]}"
    X, rho = res.x, [np.asarray(r, np.float64) for r in res.rho]
    warm: list = [None] * len(cams)
    info: dict = {}
    rounds = params.final_rounds if tv else 1
    for k in range(rounds):
        if tv:
            for p, c in enumerate(cams):
                warm[p] = tv_albedo(c["A"], c["Y"], X, rho[p], c["fixed"], c["tr"].pixel_index[c["rows"]],
                                    c["tr"].image_shape, params.albedo_tv, warm=warm[p])
                rho[p] = warm[p].rho
        # a round's envmaps only feed the next albedo step, except the last one's: fewer reweightings before it
        steps = params.edge_steps if k == rounds - 1 else min(params.edge_steps, FINAL_EARLY_STEPS)
        X, info = final_envmaps(cams, rho, grid, texel_index, params, ls, steps)
    info["ls_source"] = source
    info["rounds"] = rounds
    info["albedo_tv"] = ({"contrast": params.albedo_tv, "lam": [t.lam for t in warm],
                          "iterations": [t.iterations for t in warm], "edges": [t.edges for t in warm],
                          "regions": [t.regions for t in warm]}
                         if tv else None)
    return X, rho, info


def final_envmaps(cams: list[dict], rhos: list[np.ndarray], grid: EnvGrid, texel_index: np.ndarray,
                  params: SolveParams, ls: float, steps: int | None = None):
    """Every illumination's envmap at the albedo ``rhos`` (per camera (M_p, 3)), held fixed: the known-albedo
    solve (the prior of objcam.solvers.plan.known.solve_known_edges: tone-weighted edges at the relative weight
    ``ls``, its basis; ``steps`` reweightings, None: params.edge_steps) of ``y_lc = diag(rho_pc) A'_p x_lc``
    stacked over the problem's cameras. One Gram matrix per channel serves every illumination. Returns
    (X (N, L, 3), info for solve.json)."""
    L, n = cams[0]["Y"].shape[1], texel_index.size
    rhos = [np.asarray(r, np.float64) for r in rhos]  # (M_p, 3)
    grams = [weighted_gram([c["A"] for c in cams], [r[:, ch] ** 2 for r in rhos], n, fast=True) for ch in range(3)]
    rhs = np.zeros((n, L, 3))
    yy = np.zeros((L, 3))
    for c, rho in zip(cams, rhos):
        W = (rho[:, None, :] * c["Y"]).reshape(rho.shape[0], -1)  # (M, L * 3): rho_c y_lc
        rhs += solvers.rhs(c["A"], W, fast=True).reshape(n, L, 3)
        yy += np.einsum("mlc,mlc->lc", c["Y"], c["Y"])
    with single_blas_thread():
        ls_abs, lr_abs = solvers.absolute_weights(sum(grams) / 3, ls, params.lr)
        D = solvers.difference_operator(grid, texel_index)
        eps = params.edge_eps if params.edge_eps is not None else EDGE_EPS_KNOWN
        P = texel_basis(grid, texel_index, texel_group(params, known=True))
        X = np.zeros((n, L, 3))
        kkt = np.zeros((L, 3))
        hist = []

        def one(l: int):  # the illuminations' solves are independent: a thread per core (LAPACK releases the GIL)
            return solve_edges(grams, [rhs[:, l, ch:ch + 1] for ch in range(3)], [[0], [1], [2]], yy[l], D, ls_abs,
                               lr_abs, steps=params.edge_steps if steps is None else steps, eps_rel=eps,
                               tone=params.edge_tone, tone_floor=params.edge_tone_floor, basis=P)

        for l, r in enumerate(parallel_map(one, range(L))):
            X[:, l, :] = r.x
            kkt[l] = [np.max(q.kkt_residual) for q in r.results]
            hist.append(r.objective_history)
    return X, {"ls_relative": ls, "prior": "edges", "edge_eps": eps, "tone": params.edge_tone,
               "texel_group": texel_group(params, known=True), "kkt_residual_max": float(kkt.max()),
               "objective_history": hist}

