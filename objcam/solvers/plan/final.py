"""Unknown albedo, the final step (``final_envmap=known``): after the joint solve, rounds of the albedo's exact
step with a total-variation prior (objcam.solvers.albedo_tv: a free per-pixel albedo absorbs what the envmap
estimate gets wrong as faint shadows, which a print's piecewise-constant albedo does not have) and every envmap at
that albedo, held fixed, by the known-albedo solver (tone-weighted edges, ls from the noise). The prior's contrast
is chosen by generalised cross-validation on the noise-weighted fit (objcam.solvers.albedo_gcv,
``albedo_tv_rule=gcv``): a uniform support merges into one region, a print keeps its dots."""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from objcam import solvers
from objcam.envmap import EnvGrid
from objcam.solvers.albedo_gcv import ladder, score, weighted_chi2
from objcam.solvers.albedo_tv import tv_albedo
from objcam.solvers.basis import restrict_weak, solved_edges, texel_basis
from objcam.solvers.edges import solve_edges
from objcam.solvers.joint import weighted_gram
from objcam.solvers.joint.blocks import DEFAULT_RHO_MIN
from objcam.solvers.joint.groups import labels, least_squares_values, set_values
from objcam.solvers.joint.scale_step import known_pixel_scale
from objcam.solvers.plan.defaults import ALBEDO_TV_FACTOR, ALBEDO_TV_TOP, EDGE_EPS_KNOWN, FINAL_EARLY_STEPS
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.rules import fitted_noise, noise_weights, relative_column_norms, texel_group
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
        got = [noise_weights(scene.target(t), data[t].pooled, data[t].pooled_ok, params, c["tr"].downsample,
                             linear=True) for c in cams for t in c["targets"]]
        ls, source = float(np.median([g[0] for g in got])), f"median over the targets of {got[0][2]}"
        if params.lr is None:  # the ridge follows the noise as for a known albedo (objcam.solvers.plan.rules)
            params = params.model_copy(update={"lr": float(np.median([g[1] for g in got]))})
    X, rho = res.x, [np.asarray(r, np.float64) for r in res.rho]
    warm: list = [None] * len(cams)
    info: dict = {}
    rounds = params.final_rounds if tv else 1
    contrast, first, chosen = params.albedo_tv, 0, None
    if tv and params.albedo_tv_rule == "gcv":
        # round 0 of every candidate contrast; the rounds after it at the one GCV chose
        steps = params.edge_steps if rounds == 1 else min(params.edge_steps, FINAL_EARLY_STEPS)
        X, rho, warm, info, chosen = choose_contrast(scene, data, cams, X, rho, grid, texel_index, params, ls, steps)
        contrast, first = chosen["contrast"], 1
    for k in range(first, rounds):
        if tv:
            for p, c in enumerate(cams):
                warm[p] = tv_albedo(c["A"], c["Y"], X, rho[p], held(c), c["tr"].pixel_index[c["rows"]],
                                    c["tr"].image_shape, contrast, warm=warm[p])
                rho[p] = warm[p].rho
            uniform_step(cams, X, rho)
        # a round's envmaps only feed the next albedo step, except the last one's: fewer reweightings before it
        steps = params.edge_steps if k == rounds - 1 else min(params.edge_steps, FINAL_EARLY_STEPS)
        X, info = final_envmaps(cams, rho, grid, texel_index, params, ls, steps)
    pinned = None
    if params.pinned_scale and params.method == "exact" and any(c["fixed"].any() for c in cams):
        # the scale the pixels of known albedo pin, as the joint solve ends (scale_step.pinned_scale): the rounds
        # solve the envmaps at the free pixels' albedo, whose level then sets theirs (measured on issue 29's dark
        # object: its pixels 2-3% under-predicted after the support merged into one region)
        f = known_pixel_scale([c["A"] for c in cams], [c["Y"] for c in cams], rho, X, [c["fixed"] for c in cams])
        X = X / f[None, None, :]
        rho = [np.where(c["fixed"][:, None], r, np.clip(r * f[None, :], DEFAULT_RHO_MIN, 1.0))
               for c, r in zip(cams, rho)]
        pinned = [float(v) for v in f]
    info["ls_source"] = source
    info["rounds"] = rounds
    info["pinned_scale"] = pinned
    info["albedo_tv"] = ({"contrast": contrast, "rule": params.albedo_tv_rule, "lam": [t.lam for t in warm],
                          "iterations": [t.iterations for t in warm], "edges": [t.edges for t in warm],
                          "regions": [t.regions for t in warm], "gcv": chosen}
                         if tv else None)
    return X, rho, info


def held(c: dict) -> np.ndarray:
    """(M,) bool: camera ``c``'s pixels the TV step leaves alone: of known albedo, or on a surface of one unknown
    albedo (those take their group's value, :func:`uniform_step`)."""
    g = c.get("groups")
    return c["fixed"] if g is None else c["fixed"] | (g > 0)


def uniform_step(cams: list[dict], X: np.ndarray, rho: list[np.ndarray]) -> None:
    """Each uniform surface's one albedo by least squares at the envmaps X over every camera (in place; the final
    step's counterpart of the joint solve's group step, objcam.solvers.joint.groups)."""
    groups = [c.get("groups") for c in cams]
    if all(g is None for g in groups):
        return
    vals = least_squares_values([c["A"] for c in cams], [c["Y"] for c in cams], X, groups, DEFAULT_RHO_MIN)
    set_values(rho, groups, vals)


def target_sigmas(scene, data, cams: list[dict]) -> list[np.ndarray]:
    """Per camera (L,) the absolute noise of each of its targets at the fitted pixels: the relative noise
    (objcam.solvers.plan.rules.fitted_noise: noise_sigma, else estimated; equal for every target when neither is
    known) times the target's median positive value (objcam.transport.auto.absolute_noise)."""
    from objcam.transport.auto import absolute_noise

    out = []
    for c in cams:
        sig = []
        for t in c["targets"]:
            rel, _ = fitted_noise(scene.target(t), data[t].pooled, data[t].pooled_ok, c["tr"].downsample)
            sig.append(max(absolute_noise(data[t].y, rel or 1.0), 1e-30))
        out.append(np.asarray(sig))
    return out


def choose_contrast(scene, data, cams: list[dict], X0: np.ndarray, rho0: list[np.ndarray], grid: EnvGrid,
                    texel_index: np.ndarray, params: SolveParams, ls: float, steps: int):
    """The TV prior's contrast by GCV (objcam.solvers.albedo_gcv): for each contrast of the ladder from
    ``params.albedo_tv`` (x ALBEDO_TV_FACTOR up to ALBEDO_TV_TOP) the TV albedo at the joint solve's envmaps X0 and
    every envmap at it (``steps`` reweightings), scored by GCV on the noise-weighted fit; stops when the score rises
    or the regions stop merging. Returns the best candidate's (X, rho, TV results per camera, final_envmaps info)
    and the record {contrast, candidates}."""
    sig = target_sigmas(scene, data, cams)
    n_fixed = sum(int(held(c).sum()) for c in cams)
    n_groups = len(labels([c.get("groups") for c in cams]))  # each one region of its own
    best, cands, prev = None, [], [None] * len(cams)
    for contrast in ladder(params.albedo_tv, ALBEDO_TV_TOP, ALBEDO_TV_FACTOR):
        # warm-started from the previous contrast's TV solution (its dual is feasible for a larger weight)
        t0 = time.perf_counter()
        tvs = [tv_albedo(c["A"], c["Y"], X0, rho0[p], held(c), c["tr"].pixel_index[c["rows"]],
                         c["tr"].image_shape, contrast, warm=prev[p]) for p, c in enumerate(cams)]
        rho = [t.rho for t in tvs]
        uniform_step(cams, X0, rho)
        regions = sum(t.regions if t.regions is not None else t.rho.shape[0] for t in tvs) - n_fixed + n_groups
        if cands and regions == cands[-1].regions:
            break  # the same partition: nothing left to merge
        t1 = time.perf_counter()
        X, env_info = final_envmaps(cams, rho, grid, texel_index, params, ls, steps)
        chi2, n = weighted_chi2([c["A"] for c in cams], [c["Y"] for c in cams], rho, X, sig)
        cand = score(contrast, regions, chi2, n, 3)
        cand.seconds = (round(t1 - t0, 2), round(time.perf_counter() - t1, 2))
        cand.iterations = [t.iterations for t in tvs]
        cands.append(cand)
        if best is not None and cand.gcv > best[0].gcv:
            break  # past the minimum
        best = (cand, X, rho, tvs, env_info)
        prev = tvs
    cand, X, rho, tvs, env_info = best
    return X, rho, tvs, env_info, {"contrast": cand.contrast, "candidates": [c.record() for c in cands]}

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
        ls_abs, lr_abs = solvers.absolute_weights(sum(grams) / 3, ls, params.ridge)
        eps = params.edge_eps if params.edge_eps is not None else EDGE_EPS_KNOWN
        P = texel_basis(grid, texel_index, texel_group(params, known=True))
        weak = final_weak(cams, grams, grid, texel_index, params)
        if weak is not None:  # held to params.weak_texels, as the known-albedo solve holds them
            P = restrict_weak(grid, texel_index, P, weak, params.weak_texels)
        D = solved_edges(solvers.difference_operator(grid, texel_index), P)
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
    solved = np.ones(n, bool) if P is None else sp.csr_matrix(P).getnnz(axis=1) > 0
    return X, {"ls_relative": ls, "lr_relative": params.ridge, "prior": "edges", "edge_eps": eps,
               "tone": params.edge_tone, "texel_group": texel_group(params, known=True),
               "kkt_residual_max": float(kkt.max()),
               "objective_history": hist, "solved": solved,
               **({"weak_texels": params.weak_texels, "texels_weak": int(weak.sum())} if weak is not None else {})}


def final_weak(cams: list[dict], grams: list[np.ndarray], grid: EnvGrid, texel_index: np.ndarray,
               params: SolveParams) -> np.ndarray | None:
    """(N,) bool: the texels the final problem barely sees, by the known-albedo rule (rules.weak_texels: relative
    column norm under params.weak_fraction) on its own Gram matrices ``grams`` (3 x (N, N), A = diag(rho) A'
    stacked over the cameras); None when they are kept or an A is supersampled (as known.known_weak)."""
    # supersampled: an A finer than its output; a bare problem (no transport, or one without those sizes) is not
    sizes = [(getattr(c.get("tr"), "output_height", None), getattr(c.get("tr"), "env_height", None)) for c in cams]
    if params.weak_texels == "keep" or any(o != e for o, e in sizes):
        return None
    diag = sum(np.diagonal(g) for g in grams) / len(grams)
    dirs = grid.directions().reshape(-1, 3)[texel_index]
    return relative_column_norms(np.asarray(diag, np.float64), dirs) < params.weak_fraction

