"""Known albedo: every target's envmap from its own photo, one exact solve per target.

    min_x ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2,  x >= 0,  per colour channel,

solved in the Gram form on the merged envmap basis (objcam.solvers.basis). The steps, per target:

1. :func:`choose_ls`: the smoothness and ridge weights (given, from the target's noise, or by an auto_reg rule);
2. the solve: :func:`solve_known_edges` for the default edge-preserving prior (objcam.solvers.edges; with a grey
   A the luminance from the solve at ls and the chroma from a second one at ``chroma_ls_factor`` x ls,
   objcam.solvers.chroma, on a second thread; a supersampled A on the adaptive basis of objcam.solvers.refine), or
   :func:`solve_known_quadratic` for the quadratic prior and the method's damped solver (one Gram matrix serves
   every channel of a grey A and every target that shares A and its usable pixels);
3. :func:`known_solution`: the envmap on the lat-long grid (area-averaged to the output grid for a supersampled
   A), the predicted image and solve.json's record.
"""

from __future__ import annotations

import copy
import time

import numpy as np
import scipy.sparse as sp

from objcam import solvers
from objcam.envmap import EnvGrid
from objcam.solvers.basis import MERGE_BLOCK_BYTES, merge_gram, restrict_weak, solved_edges, texel_basis, unknowns
from objcam.solvers.chroma import luminance_with_chroma
from objcam.solvers.edges import EdgeResult, solve_edges
from objcam.solvers.lowrank import gram_lowrank, lowrank_update
from objcam.solvers.nnls import PCG_MIN_UNKNOWNS
from objcam.solvers.outliers import brightness_weights, outlier_rows
from objcam.solvers.plan.defaults import EDGE_EPS_KNOWN, OUTLIER_AFTER_STEPS, OUTLIER_CLEAN_SPREAD, OUTLIER_MAX_SHARE
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.rules import (
    basis_info,
    discrepancy_sigma,
    fitted_noise,
    noise_scale,
    noise_weights,
    placed_texels,
    texel_group,
    weak_texels,
)
from objcam.solvers.plan.targets import TargetData, TargetSolution, texel_mask
from objcam.solvers.plan.verdict import black_light, chi2_per_value, dark_sky, dark_sky_area
from objcam.solvers.refine import average_to, coarse_of, contrast, refined_basis, split_by_contrast
from objcam.solvers.skyprofile import (
    floor_step,
    misfit_allowance,
    profile_basis,
    profile_fit_kept,
    row_curvature_edges,
    sky_profile,
)
from objcam.solvers.sources import fit_residual
from objcam.threads import blas_threads, parallel_map, single_blas_thread


def solve_known(scene, data: dict[str, TargetData], params: SolveParams,
                names: list[str]) -> dict[str, TargetSolution]:
    """The targets ``names`` of ``scene`` (objcam.schemas.artifacts.SceneArtifact), each solved on its own."""
    gram_cache: dict[tuple, tuple] = {}  # shared by the targets of one camera and valid mask
    return {name: _solve_target(scene.target(name), data[name], params, gram_cache) for name in names}


def _solve_target(target, d: TargetData, params: SolveParams, gram_cache: dict) -> TargetSolution:
    tr, use, y = d.transport, d.use, d.y
    grid = EnvGrid(tr.env_height)
    edges = params.prior == "edges" and params.method == "exact"
    t0, c0 = time.perf_counter(), time.process_time()
    edge_info = None
    with single_blas_thread():
        weak = known_weak(tr, params)
        ls, lr, ls_source, auto_info = choose_ls(target, d, grid, params, linear=edges)
        rejected = profile = None
        if edges:
            sigma_abs = noise_per_value(target, d) if params.outliers != "keep" else None
            X, kkt, obj, iters, edge_info, rejected = solve_known_edges(tr, grid, use, y, ls, lr, params,
                                                                        weak, sigma_abs)
            fitted = use if rejected is None else use & ~rejected
            noise_fit = fit_noise(target, d, fitted, X, params, weak)
            if noise_fit is not None and noise_fit["factor"] < 1.0:  # the photo is less noisy than stated
                quieter = _with_noise(target, noise_fit["noise_sigma"])
                ls, lr, ls_source, auto_info = choose_ls(quieter, d, grid, params, linear=edges)
                ls_source += f" (fitted: {noise_fit['factor']:.3g} x the stated noise)"
                sigma_abs = noise_per_value(quieter, d) if params.outliers != "keep" else None
                X, kkt, obj, more, edge_info, rejected = solve_known_edges(tr, grid, use, y, ls, lr, params,
                                                                           weak, sigma_abs)
                iters += more
                fitted = use if rejected is None else use & ~rejected
            if params.sky_profile != "off":  # issues 22, 28: azimuthal detail the data cannot tell from none
                X, kkt, obj, iters, edge_info, rejected, profile = with_sky_profile(
                    tr, grid, d, fitted, X, (kkt, obj, iters, edge_info, rejected), (ls, lr), params, weak, sigma_abs)
            if params.sources != "off":  # issues 22, 28: a source the photo places better than the prior's spread
                # on every usable pixel: the outlier rounds drop the shadow edges a spread lamp misfits, which
                # are the photo's evidence of where it is (lamp30_r0_n2: the fall 3.5 x the need on all, 0.3 x
                # on the pixels kept); a pixel no map fits (a hot one) only raises the need
                X, edge_info["sources"] = known_sources(tr, grid, use, y, X, noise_per_value(target, d))
            if noise_fit is not None:
                edge_info["noise_fit"] = noise_fit
        else:
            X, kkt, obj, iters = solve_known_quadratic(tr, grid, use, y, ls, lr, params, gram_cache, weak)
    solve_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    # CPU beside wall: on a shared machine the wall time says more about the load than about the solve
    info = {"channels_in_A": int(tr.A.shape[0]), "solve_seconds": round(solve_s, 4),
            "solve_cpu_seconds": round(cpu_s, 4),
            "iterations": int(iters), "kkt_residual_max": float(kkt.max()), "objective": obj.tolist(),
            "ls_relative": ls, "lr_relative": lr, "ls_source": ls_source}
    sol = known_solution(tr, grid, d if rejected is None else d._replace(use=use & ~rejected), X, params, info,
                         edge_info, auto_info, weak)
    sol.rejected, sol.profile = rejected, profile
    return sol


def known_sources(tr, grid: EnvGrid, use: np.ndarray, y: np.ndarray, X: np.ndarray, sigma_abs: float | None
                  ) -> tuple:
    """params.sources=compact (objcam.solvers.sources) on the usable pixels ``use`` (M,) bool, ``sigma_abs`` the
    stated noise of one pixel value: (X (N, 3), its record for solve.json's edges)."""
    from objcam.solvers.sources import compact_sources

    got = compact_sources(tr.A, use, y, X, grid, tr.texel_index, tr.solid_angle, sigma_abs)
    return got.x, got.info


def with_sky_profile(tr, grid: EnvGrid, d: TargetData, fitted: np.ndarray, X: np.ndarray, solved: tuple,
                     weights: tuple[float, float], params: SolveParams, weak: np.ndarray | None,
                     sigma_abs: float | None) -> tuple:
    """params.sky_profile=auto (objcam.solvers.skyprofile) after the edge solve ``solved`` = (KKT, objective,
    iterations, edge record, rejected rows) of X (N, 3) at ``weights`` = (ls, lr), on the pixels ``fitted`` it
    fitted: where the row means' test fails, the profile model's own fit tested (step 3b); where a test keeps the
    profile, the envmap solved again on the profile model (step 4; a supersampled A keeps the row means and has no
    step 3b). Returns (X, KKT, objective, iterations, edge record with ``sky_profile``, rejected rows, the (N,) bool
    texels given as their row's value or None)."""
    kkt, obj, iters, edge_info, rejected = solved
    X0 = X  # the edge solve's map
    P = known_basis(tr, params, weak=weak)
    inside = np.ones(len(tr.texel_index), bool) if P is None else sp.csr_matrix(P).getnnz(axis=1) > 0
    got = sky_profile(tr.A, fitted, d.y, X, grid, tr.texel_index, inside, tr.solid_angle)
    rec = got.info
    if got.candidate is not None and tr.output_height == tr.env_height:
        basis = profile_basis(P, tr.texel_index, grid, got.candidate)
        keep = got.sky is not None
        if not keep:  # the test on the profile model's own fit, not on the solved map's row means
            plain = params.model_copy(update={"outliers": "keep"})  # on the pixels the map fitted
            xp = solve_known_edges(tr, grid, fitted, d.y, *weights, plain, weak, sigma_abs, basis=basis)[0]
            ss_fit = fit_residual(tr.A, fitted, d.y[fitted], xp)[1]
            # the map's row means are a member of the profile model too: the model's fit is the better of the two
            # (at the map's prior its solved member can fit worse: lamp85_r0_n2 199 spreads, its row means 20.7)
            ss_model = min(ss_fit, rec["ss_profile"])
            allow, excess = misfit_allowance(rec["ss_map"], rec["fitted_values"], sigma_abs)
            keep = profile_fit_kept(ss_model - rec["ss_map"], rec["ss_spread"], allow, rec["blobs"])
            spread = max(rec["ss_spread"], 1e-300)
            rec.update({"ss_profile_fitted": ss_fit, "ss_profile_model": ss_model, "ss_excess": excess,
                        "ss_allowed": allow, "taken": bool(keep),
                        "fitted_rise_over_spread": float((ss_fit - rec["ss_map"]) / spread),
                        "model_rise_over_spread": float((ss_model - rec["ss_map"]) / spread)})
        if keep:
            # (step 3b tested the model at the map's own prior; its rows' levels are estimated as one smooth profile)
            X, kkt, obj, more, edge_info, rejected = solve_known_edges(tr, grid, d.use, d.y, *weights, params,
                                                                       weak, sigma_abs, basis=basis,
                                                                       sky_rows=got.candidate & inside)
            iters += more
            rec["resolved"] = {"unknowns": int(basis.shape[1])}
            # step 5: no source or rim darker than the sky behind it (the fit's answer to a lamp's sub-texel shadows)
            fit4 = d.use if rejected is None else d.use & ~rejected
            X, rec["floor"] = floor_step(tr.A, fit4, d.y[fit4], X, basis, got.candidate,
                                         np.asarray(tr.texel_index, np.int64) // grid.width, tr.solid_angle,
                                         sigma_abs)
        profile = got.candidate if keep else None
    else:  # no sky texel, or a supersampled A: the row means where their test kept them
        X, profile = got.x, got.sky
    if profile is not None:  # the black the edge solve left, which the profile fills: the verdict still sees it
        up, omega = tr.directions[:, 2] > 0, tr.solid_angle.astype(np.float64)
        rec["dark_sky_area_solved"] = dark_sky_area(X0.mean(axis=1), omega, up & inside)
        # the light the black the edge solve left would hold at the final map's sky level
        rec["dark_sky_light_solved"] = black_light(X.mean(axis=1), omega, dark_sky(X0.mean(axis=1), up & inside),
                                                   up & inside)
    edge_info["sky_profile"] = rec
    return X, kkt, obj, iters, edge_info, rejected, profile


def fit_noise(target, d: TargetData, fitted: np.ndarray, X: np.ndarray, params: SolveParams,
              weak: np.ndarray | None) -> dict | None:
    """solve.noise_fit=auto: the record {chi2_stated, expected, factor, noise_sigma} of the edge solve's map X
    (N, 3) on the pixels ``fitted`` (M,) bool against the target's stated (or estimated) noise
    (objcam.solvers.plan.rules.noise_scale: factor < 1 when the residual is significantly below that noise;
    noise_sigma: the per-photo-pixel relative noise the residual supports); None when off, when ls is not set
    from the noise (given, or an auto_reg rule) or when the noise is unknown."""
    tr = d.transport
    sigma_rel, _ = fitted_noise(target, d.pooled, d.pooled_ok, tr.downsample)
    from_noise = params.ls is None and params.auto_reg == "off"
    if params.noise_fit == "off" or not from_noise or not sigma_rel or not fitted.any():
        return None
    r, _ = fit_residual(tr.A, fitted, d.y[fitted], X)
    chi2, _ = chi2_per_value(d.y[fitted], d.y[fitted] - r, sigma_rel)
    factor, expected = noise_scale(chi2, r.size, unknowns(tr.texel_index, known_basis(tr, params, weak=weak)))
    return {"chi2_stated": round(chi2, 5), "expected": round(expected, 5), "factor": round(factor, 5),
            "noise_sigma": sigma_rel * max(int(tr.downsample), 1) * factor}


def _with_noise(target, noise_sigma: float):
    """A copy of the target (a pydantic model, or any object with attributes) with another ``noise_sigma``."""
    if hasattr(target, "model_copy"):
        return target.model_copy(update={"noise_sigma": noise_sigma})
    out = copy.copy(target)
    out.noise_sigma = noise_sigma
    return out


def noise_per_value(target, d: TargetData) -> float | None:
    """The stated noise of one fitted pixel value in absolute units (the target's noise_sigma over the pooling,
    else estimated from the image, times the median pixel: objcam.transport.auto.absolute_noise); None when
    unknown."""
    from objcam.transport.auto import absolute_noise

    sigma_rel, _ = fitted_noise(target, d.pooled, d.pooled_ok, d.transport.downsample)
    return absolute_noise(d.y[d.use], sigma_rel) if sigma_rel else None


def known_weak(tr, params: SolveParams) -> np.ndarray | None:
    """(N,) bool: A's texels held to params.weak_texels (rules.weak_texels), found once per target; None when
    they are kept or the A is supersampled (its refined basis does not hold them apart)."""
    if params.weak_texels == "keep" or tr.output_height != tr.env_height:
        return None
    return weak_texels(tr, params.weak_fraction)


def choose_ls(target, d: TargetData, grid: EnvGrid, params: SolveParams, linear: bool):
    """The relative smoothness and ridge weights: params.ls, else from the target's noise
    (objcam.solvers.plan.rules.noise_weights; ``linear``: the edge prior's rule), replaced by the auto_reg rule's
    choice unless it is off; params.lr, else for the edge prior with ls from the noise the noise's ridge
    (rules.noise_lr), else the fixed default. Returns (ls, lr, the source of ls, the auto_reg record or None).
    Call with one BLAS thread."""
    tr, use, y = d.transport, d.use, d.y
    C = tr.A.shape[0]
    rule = params.auto_reg if params.auto_reg != "off" else None
    auto_info = None
    ls, ls_source = params.ls, "param"
    lr = params.ridge
    if ls is None:
        ls, noise_ridge, ls_source = noise_weights(target, d.pooled, d.pooled_ok, params, tr.downsample,
                                                   linear=linear, supersample=tr.env_height // tr.output_height,
                                                   height=tr.output_height)
        if linear and params.lr is None and rule is None:
            lr = noise_ridge
    if rule is not None:
        # one weight for the target's channels: the criterion on the grey (channel-mean) transport
        Ag = tr.A[0][use] if C == 1 else tr.A[:, use].mean(axis=0)
        ls, _, inf = solvers.choose_weights(Ag, y[use], grid, tr.texel_index, rule=rule,
                                            sigma=discrepancy_sigma(target, y[use], rule), lr=lr)
        auto_info = {"rule": rule, "ls_relative": ls, "notes": inf["notes"], "seconds": round(inf["seconds"], 3)}
        ls_source = f"auto_reg {rule}"
    return ls, lr, ls_source, auto_info


def solve_known_quadratic(tr, grid: EnvGrid, use: np.ndarray, y: np.ndarray, ls: float, lr: float,
                          params: SolveParams, gram_cache: dict, weak: np.ndarray | None = None):
    """The quadratic prior (method exact: bound-constrained minimiser; paper: the method's damped steps), per
    channel of A. ``gram_cache`` keeps the regularised Gram matrix per (A, channel, usable pixels, weights);
    ``weak``: :func:`known_weak`. Returns X (N, 3), KKT residual (3,), objective (3,), iterations."""
    C = tr.A.shape[0]
    X, kkt, obj, iters = np.zeros((tr.A.shape[2], 3)), np.zeros(3), np.zeros(3), 0
    grams = None
    for c in range(C):
        # one Gram matrix per (A, channel, usable pixels, weights): shared by every channel of a grey A
        # and by every target that shares the camera and the valid mask
        key = (str(tr.folder), c, hash(use.tobytes()), ls, lr)
        Ac = tr.A[c] if use.all() else tr.A[c][use]  # a mask copies A's 16k x 1k floats
        if key not in gram_cache:
            # the transport stage stored A^T A over all kept pixels; remove the few excluded rows
            grams = tr.gram() if grams is None else grams
            G = grams[c]
            if not use.all():
                G = G - solvers.gram(tr.A[c][~use])
            ls_abs, lr_abs = solvers.absolute_weights(G, ls, lr)
            P = known_basis(tr, params, weak=weak)
            D = solved_edges(solvers.difference_operator(grid, tr.texel_index), P)
            Q = solvers.regularized_gram(G, D, ls_abs, lr_abs)
            gram_cache[key] = (Q, None) if P is None else (merge_gram(P, Q), P)
        Q, P = gram_cache[key]
        chans = [0, 1, 2] if C == 1 else [c]
        Yc = y[use][:, chans]
        B = solvers.rhs(Ac, Yc, fast=True)
        if P is not None:  # the same objective over x = P z: P^T Q P, P^T b (objcam.solvers.basis)
            B = np.asarray(P.T @ B)
        res = (solvers.solve_exact if params.method == "exact" else solvers.solve_paper)(Q, B)
        X[:, chans] = res.x if P is None else np.asarray(P @ res.x.reshape(P.shape[1], -1))
        kkt[chans], iters = res.kkt_residual, max(iters, res.iterations)
        obj[chans] = solvers.objective(Q, B, res.x, np.einsum("ij,ij->j", Yc, Yc))
    return X, kkt, obj, iters


def known_basis(tr, params: SolveParams, split: np.ndarray | None = None, weak: np.ndarray | None = None):
    """The known-albedo solve's basis P over A's texels (None: the texels): the merged basis
    (objcam.solvers.basis), or for a supersampled A the output texels with ``split`` of them refined
    (objcam.solvers.refine; None: none refined)."""
    g = texel_group(params, known=True)
    if tr.output_height == tr.env_height:
        P = texel_basis(tr.grid, tr.texel_index, g, alone=placed_texels(tr))
        if params.weak_texels == "keep":
            return P
        if weak is None:  # (N,) bool: the texels held to params.weak_texels (:func:`known_weak`)
            weak = weak_texels(tr, params.weak_fraction)
        return restrict_weak(tr.grid, tr.texel_index, P, weak, params.weak_texels)
    if split is None:
        split = np.zeros(coarse_of(tr.grid, tr.texel_index, tr.output_height)[0].size, bool)
    return refined_basis(tr.grid, tr.texel_index, tr.output_height, split, g)


def known_solution(tr, grid: EnvGrid, d: TargetData, X: np.ndarray, params: SolveParams, solve: dict,
                   edge_info: dict | None, auto_info: dict | None, weak: np.ndarray | None) -> TargetSolution:
    """The target's envmap, prediction and solve.json from X (N, 3) on A's texels; ``solve``: the solve's own
    record (channels_in_A, solve_seconds, iterations, kkt_residual_max, objective, ls_relative, ls_source);
    ``weak``: :func:`known_weak`."""
    use, y = d.use, d.y
    env = tr.envmap_from_x(X)
    P = known_basis(tr, params, weak=weak)
    solved = tr.texel_index if P is None else tr.texel_index[sp.csr_matrix(P).getnnz(axis=1) > 0]
    mask = texel_mask(grid, solved)  # weak texels excluded (weak_texels=exclude) are not solved
    fine = None
    if tr.output_height != tr.env_height:  # supersampled A: write the area average (objcam.solvers.refine)
        fine = (env, mask)
        env, mask = average_to(env, mask, tr.output_height)
    pred = tr.predict(X)
    fit = pred.reshape(-1, 3)[tr.pixel_index][use]
    rel_res = float(np.linalg.norm(fit - y[use]) / max(np.linalg.norm(y[use]), 1e-30))
    info = {
        "method": params.method, "albedo": "known", "texels": int(len(tr.texel_index)),
        **basis_info(tr.texel_index, P, params, known=True),
        **({"weak_texels": params.weak_texels, "texels_weak": int(weak.sum())} if weak is not None else {}),
        "pixels_used": int(use.sum()), "pixels_excluded": int((~use).sum()),
        "channels_in_A": solve["channels_in_A"], "solve_seconds": solve["solve_seconds"],
        "solve_cpu_seconds": solve["solve_cpu_seconds"], "iterations": solve["iterations"],
        "kkt_residual_max": solve["kkt_residual_max"],
        "objective": solve["objective"], "relative_image_residual": rel_res, "ls_relative": solve["ls_relative"],
        "lr_relative": solve["lr_relative"], "ls_source": solve["ls_source"],
        "prior": params.prior if params.method == "exact" else "smooth",
    }
    if edge_info is not None:
        info["edges"] = edge_info
    if auto_info:
        info["auto_reg"] = auto_info
    if fine is not None:
        info["supersample"] = {"a_height": tr.env_height, "output_height": tr.output_height,
                               **(edge_info.pop("refine", {}) if "edges" in info else {})}
    return TargetSolution(env, mask, pred, info, fine=fine)


def solve_known_edges(tr, grid: EnvGrid, use: np.ndarray, y: np.ndarray, ls: float, lr: float,
                      params: SolveParams, weak: np.ndarray | None = None, sigma_abs: float | None = None,
                      basis: sp.spmatrix | None = None, sky_rows: np.ndarray | None = None):
    """Known albedo, edge-preserving prior (objcam.solvers.edges): X (N, 3), KKT, objective, steps, info and the
    (M,) bool rows of A dropped as outliers (None when none were; params.outliers, objcam.solvers.outliers, with
    ``sigma_abs`` the stated noise of one fitted value, None when unknown). ``basis``: the envmap basis (N, N')
    to solve on instead of :func:`known_basis`'s (objcam.solvers.skyprofile.profile_basis; not with a
    supersampled A). ``sky_rows``: (N,) bool, the texels ``basis`` gives one unknown per row (the profile's sky):
    the prior adds the rows' second differences (objcam.solvers.skyprofile.row_curvature_edges)."""
    grams_all = tr.gram()
    C = tr.A.shape[0]
    grams, rhs, chans = [], [], []
    Y = y[use]
    for c in range(C):
        G = grams_all[c]
        if not use.all():
            G = G - solvers.gram(tr.A[c][~use])
        ch = [0, 1, 2] if C == 1 else [c]
        grams.append(G)
        rhs.append(solvers.rhs(tr.A[c] if use.all() else tr.A[c][use], Y[:, ch], fast=True))
        chans.append(ch)
    G_ref = grams[0] if C == 1 else sum(grams) / C
    ls_abs, lr_abs = solvers.absolute_weights(G_ref, ls, lr)
    D = solvers.difference_operator(grid, tr.texel_index)
    eps = params.edge_eps if params.edge_eps is not None else EDGE_EPS_KNOWN
    yy = np.einsum("ij,ij->j", Y, Y)
    basis = known_basis(tr, params, weak=weak) if basis is None else basis
    D = solved_edges(D, basis)
    if sky_rows is not None:
        D = row_curvature_edges(D, sky_rows, tr.texel_index, grid)
    refine_info = None
    if tr.output_height != tr.env_height:
        # supersampled A (objcam.solvers.refine): a pilot quadratic solve on the output texels says where the
        # envmap has contrast; those output texels are solved on the fine grid
        pilot = solve_edges(grams, rhs, chans, yy, D, ls_abs, lr_abs, steps=0, basis=basis)
        split = split_by_contrast(contrast(grid, tr.texel_index, tr.output_height, pilot.x), params.refine_fraction)
        basis = known_basis(tr, params, split)
        refine_info = {"refine_fraction": params.refine_fraction, "refined_output_texels": int(split.sum()),
                       "output_texels": int(split.size), "unknowns": int(basis.shape[1])}
    # the chroma solve (objcam.solvers.chroma) needs one A for every channel: the luminance of X is then A's own
    split = params.chroma_ls_factor > 0 and C == 1
    weights = [ls_abs]
    if split:
        weights.append(solvers.absolute_weights(G_ref, ls * params.chroma_ls_factor, lr)[0])

    merged = basis is not None and refine_info is None
    if merged:  # once for both solves (each merged its own copy: 2 x 2.1 GB at 128 x 256)
        grams = [merge_gram(basis, G) for G in grams]
        rhs = [np.asarray(basis.T @ B) for B in rhs]
        if grams[0].shape[0] >= PCG_MIN_UNKNOWNS:
            # the PCG preconditioner's low-rank bound, once per Gram (objcam.solvers.lowrank): here on both
            # cores, where inside the solves one thread computes it while the other waits for it
            with blas_threads():
                for G in grams:
                    gram_lowrank(G)
    del grams_all, G_ref, G

    def one(w: float, steps: int, data: tuple, start: EdgeResult | None = None, warm: EdgeResult | None = None,
            keep: bool = False, continued: bool = False) -> EdgeResult:
        """solve_edges at the prior weight ``w`` for ``steps`` reweightings on ``data`` (grams, rhs, yy). start:
        the run to continue; warm: the run to warm from; keep: a later run continues or warms from this one (it
        keeps its Q buffers for that run); continued: a later run continues from this one after its steps, so its
        last step is not the answer (solve_edges' ``final``)."""
        g, b, y2 = data
        return solve_edges(g, b, chans, y2, D, w, lr_abs, steps=steps, eps_rel=eps, tone=params.edge_tone,
                           tone_floor=params.edge_tone_floor, basis=basis, merged=merged, start=start, warm=warm,
                           keep_buffers=keep, final=not continued)

    # independent solves (luminance and chroma): a thread each (the caller holds one BLAS thread)
    if params.outliers == "keep":
        runs = parallel_map(lambda w: one(w, params.edge_steps, (grams, rhs, yy)), weights)
        rejected = outlier_info = None
    else:
        runs, rejected, outlier_info = _robust_runs(one, weights, tr, use, Y, chans, sigma_abs, params,
                                                    (grams, rhs, yy), basis if merged else None)
    res = runs[0]
    kkt = np.zeros(3)
    iters = 0
    for run in runs:
        for r, ch in zip(run.results, chans):
            kkt[ch] = np.maximum(kkt[ch], r.kkt_residual)
            iters += r.iterations
    obj = np.full(3, res.objective_history[-1] / 3)
    hist = res.objective_history
    info = {"steps": res.steps, "objective_history": hist, "edge_scale": res.edge_scale, "edge_eps": eps,
            "tone": res.tone, "tone_floor": params.edge_tone_floor if res.tone > 0 else None,
            "edges_above_threshold": round(res.kept_edges, 4),
            "monotone": non_increasing(hist)}
    if refine_info:
        info["refine"] = refine_info
    if outlier_info is not None:
        info["outliers"] = outlier_info
    X = res.x
    if split:
        X = luminance_with_chroma(res.x, runs[1].x)
        hc = runs[1].objective_history
        info["chroma"] = {"ls_factor": params.chroma_ls_factor, "steps": runs[1].steps, "objective_history": hc,
                          "monotone": non_increasing(hc),
                          "black_texels_per_channel_before": [int(v) for v in (res.x <= 0).sum(axis=0)],
                          "black_texels_per_channel": [int(v) for v in (X <= 0).sum(axis=0)]}
    elif params.chroma_ls_factor > 0:
        info["chroma"] = {"ls_factor": params.chroma_ls_factor, "skipped": "A differs per channel"}
    return X, kkt, obj, iters, info, rejected


def _robust_runs(one, weights: list, tr, use: np.ndarray, Y: np.ndarray, chans: list, sigma_abs: float | None,
                 params: SolveParams, data: tuple, merged_on=None) -> tuple[list, np.ndarray | None, dict]:
    """The edge solves with outlier pixels dropped (params.outliers reject) or down-weighted (huber).

    1. OUTLIER_AFTER_STEPS edge steps on every pixel; the outliers of that fit (objcam.solvers.outliers) are a
       first set. None: the steps continue to params.edge_steps, the plain solve (a run that converged in
       fewer steps stops there).
    2. When that fit misses its ordinary pixels by more than OUTLIER_CLEAN_SPREAD x the noise (robust spread;
       or the noise is unknown), outliers bent it: a fresh solve without the set (its own quadratic start, so
       outliers do not set the edge prior's scale; warm-started), OUTLIER_AFTER_STEPS steps, and the outliers of
       its fit over every usable pixel: a pixel the contaminated first fit flagged comes back.
    3. The last solve continues on the last set to params.edge_steps.

    The first weight's run (the luminance) decides the sets from its own fit; the others (the chroma solve)
    take each set when it is ready and run on the other core meanwhile, so neither waits at a round's end for
    the other (the downdate of the Gram runs beside the chroma solve). The cost: in a second round the chroma
    run's Q may be alive during the second downdate, one N' x N' array more at the stage's peak than when the
    rounds waited for each other.

    ``one(weight, steps, (grams, rhs, yy), start=, warm=, keep=, continued=)`` runs solve_edges; ``data`` holds
    the full grams, rhs and yy, on the basis ``merged_on`` when given (N x N' 0/1). Returns (runs, rejected (M,)
    bool or None, record)."""
    from concurrent.futures import Future

    k0 = min(OUTLIER_AFTER_STEPS, params.edge_steps)
    rest = params.edge_steps - k0

    flagged = [None]  # noise_model=brightness: the outlier rows proper among the reweighted ones

    def outliers(run) -> tuple[np.ndarray, np.ndarray, dict]:
        fit = tr.predict_pixels(run.x)[use]  # (float32 products: far below the noise)
        rows, rec = outlier_rows(Y, fit, sigma_abs, params.outlier_threshold, OUTLIER_MAX_SHARE)
        w = rec.pop("weights")
        if params.noise_model == "brightness":  # every pixel weighted: the outliers' weights times the noise's
            wt = np.ones(len(Y))
            wt[rows] = w[rows] if params.outliers == "huber" else 0.0
            bw, per_bin = brightness_weights(Y, fit, sigma_abs, OUTLIER_CLEAN_SPREAD)
            wt *= bw
            flagged[0] = rows
            rec["noise_model"] = {"model": "brightness", "bin_sigma": [float(v) for v in np.sqrt(per_bin)],
                                  "weight_min": float(wt.min()), "weight_max": float(wt.max())}
            rows = wt != 1.0
            return rows, 1.0 - wt[rows], rec
        return rows, (1.0 - w[rows] if params.outliers == "huber" else np.ones(int(rows.sum()))), rec

    def without(rows: np.ndarray, drop: np.ndarray, base: tuple, base_drop: np.ndarray) -> tuple[np.ndarray, tuple]:
        """(rejected (M,), data without ``rows`` at ``drop``) from ``base``, the data at ``base_drop`` (M_use,):
        only the rows whose weight changes are touched."""
        d = np.zeros(len(Y))
        d[rows] = drop
        change = d - base_drop
        sel = change != 0
        rejected = np.zeros(use.shape, bool)
        # the rows reported as rejected (outliers.png, the verdict's chi-squared) are the outliers proper, not the
        # rows noise_model=brightness down-weights
        rejected[np.flatnonzero(use)[rows if flagged[0] is None else flagged[0]]] = True
        moved = np.zeros(use.shape, bool)
        moved[np.flatnonzero(use)[sel]] = True
        return rejected, (downdated(tr, moved, Y[sel], change[sel], *base, chans, merged_on), d)

    # what the lead run decides, for the others: after the first fit (the data to go on with, whether a second
    # round follows) and after the second (its data)
    first_set, second_set = Future(), Future()

    def lead(w) -> tuple:
        try:
            r = one(w, k0, data, keep=True, continued=rest > 0)
            rows, drop, rec = outliers(r)
            if not rows.any():
                rec["rounds"] = 1
                first_set.set_result((data, False))
                return (one(w, rest, data, start=r) if rest > 0 and r.steps == k0 else r), None, rec
            first = int(rows.sum())
            rejected, (now, d1) = without(rows, drop, data, np.zeros(len(Y)))
            if sigma_abs and rec["robust_scale"] <= OUTLIER_CLEAN_SPREAD * sigma_abs:
                # the fit explains its ordinary pixels to a few noise sigmas: the outliers did not bend it, its
                # set stands and the solve continues without it
                rec["rounds"] = 1
                first_set.set_result((now, False))
            else:
                first_set.set_result((now, True))
                # (no buffers kept: held through the second downdate they would add to the stage's peak memory)
                r = one(w, k0, now, warm=r, continued=rest > 0)
                rows, drop, rec = outliers(r)
                rec.update(rounds=2, first_round_pixels=first)
                rejected, (now, _) = without(rows, drop, now, d1)
                rejected = rejected if rows.any() else None
                second_set.set_result(now)
            if rejected is not None and not rejected.any():  # only down-weighted (noise_model), none rejected
                rejected = None
            return (one(w, rest, now, start=r) if rest > 0 else r), rejected, rec
        except BaseException as e:  # the others wait on these: they fail with it instead of hanging
            for f in (first_set, second_set):
                if not f.done():
                    f.set_exception(e)
            raise

    def follow(w):
        r = one(w, k0, data, keep=True, continued=rest > 0)
        now, again = first_set.result()
        if now is data:  # no outliers: the plain solve
            return one(w, rest, data, start=r) if rest > 0 and r.steps == k0 else r
        if again:
            r = one(w, k0, now, warm=r, continued=rest > 0)
            now = second_set.result()
        return one(w, rest, now, start=r) if rest > 0 else r

    # (one core: the lead runs to its end first, so the others never wait)
    got = parallel_map(lambda job: job[0](job[1]), [(lead, weights[0])] + [(follow, w) for w in weights[1:]])
    run, rejected, rec = got[0]
    return [run] + got[1:], rejected, rec


def downdated(tr, rows: np.ndarray, Yo: np.ndarray, drop: np.ndarray, grams: list, rhs: list, yy: np.ndarray,
              chans: list, P=None) -> tuple[list, list, np.ndarray]:
    """(grams, rhs, yy) of the data term with A's rows ``rows`` (M,) bool weighted by 1 - drop (K,) (drop 1:
    removed, negative: added back): A_c^T A_c - A_o^T diag(drop) A_o, A_c^T y - A_o^T diag(drop) y_o, per block;
    Yo (K, 3) their pixels; P: the basis (N x N') when grams and rhs are merged onto it (then A_o P). The products
    are in float64: in float32 their rounding, subtracted from a Gram matrix those rows dominate (a bright object
    down-weighted by solve.noise_model), left it numerically indefinite (KKT 1e-8 instead of 1e-15 on
    tests/test_end_to_end.py's capture)."""
    grams, rhs = list(grams), list(rhs)
    for c in range(len(grams)):
        Ao = np.asarray(tr.A[c][rows], np.float64)
        if P is not None:
            Ao = np.asarray((P.T @ Ao.T).T, np.float64)
        Aw = drop[:, None] * Ao
        G, out = grams[c], np.empty(grams[c].shape)
        # by blocks of rows: the one new N x N array and small temporaries (the whole float32 product and its
        # float64 copy were two more N x N arrays, each a fresh mapping whose pages fault in)
        step = max(1, MERGE_BLOCK_BYTES // (8 * max(G.shape[1], 1)))
        for r0 in range(0, G.shape[0], step):
            np.subtract(G[r0:r0 + step], Ao[:, r0:r0 + step].T @ Aw, out=out[r0:r0 + step])
        grams[c] = out
        U = Ao.T
        # the PCG preconditioner's low-rank bound of the new Gram from the old one's sketch (objcam.solvers.lowrank)
        lowrank_update(out, G, U, drop)
        rhs[c] = rhs[c] - U @ (drop[:, None] * Yo[:, chans[c]])
    return grams, rhs, yy - np.einsum("i,ij,ij->j", drop, Yo, Yo)


def non_increasing(history: list[float]) -> bool:
    """An objective history that never rises (to 1e-9 relative)."""
    return bool(all(b <= a * (1 + 1e-9) for a, b in zip(history, history[1:])))
