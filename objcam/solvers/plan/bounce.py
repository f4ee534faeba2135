"""The joint solve with its bounce refits: the light the support throws onto the object was gathered by the
transport at a guessed albedo; once the joint solve has estimated the albedo, that light is redone from it and the
joint solve rerun (``solve.bounce_refits``).

:func:`solve_with_refits` is the sequence: a first solve (stopped early, quadratic prior, on one pixel in
``first_solve_stride``^2 when a refit follows: :func:`subsample`, :func:`solve_subsampled`), then each refit
(:func:`refit_bounce`) and the solve from the refitted A', the last one at the requested tolerance.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from objcam.envmap import EnvGrid
from objcam.solvers.joint import albedo_at
from objcam.solvers.joint.groups import set_values, values_of
from objcam.solvers.jointauto import JointSetup, solve_joint_auto
from objcam.solvers.plan.defaults import BOUNCE_FIRST_TOL, BOUNCE_LEVELS
from objcam.solvers.plan.params import SolveParams
from objcam.transport.gather import bounce_delta


def solve_with_refits(cams: list[dict], comp, grid: EnvGrid, setup: JointSetup, params: SolveParams, sigma):
    """The joint solve of the cameras ``cams`` (objcam.solvers.plan.unknown.camera_blocks; their A' is replaced
    in place by each refit) at ``setup``, with ``params.bounce_refits`` refits where the transport gathered the
    interreflections. Returns (JointResult, the auto_reg record or None, one record per refit and camera)."""
    L = cams[0]["Y"].shape[1]

    def solve(rho, stp):
        """The joint solve of this problem's cameras (their current A') from the albedo ``rho`` (one per camera)."""
        return solve_joint_auto([(c["A"], c["Y"], c["tr"].pixel_index[c["rows"]], c["tr"].image_shape, r,
                                  c["fixed"], c.get("groups")) for c, r in zip(cams, rho)], grid, comp.texel_index,
                                stp, sigma=sigma)

    t0 = time.perf_counter()
    # also when the envmap is unconstrained: its shape comes from the priors, but the refit makes A's
    # interreflections reflect the surfaces at the albedo the solve writes, so that a renderer given the solve's
    # albedo and envmap (objcam export) reproduces its prediction (issue 23)
    refit_next = (params.bounce_refits > 0 and params.method == "exact"
                  and any(c["tr"].has_bounce_parts for c in cams))
    # a bounce refit follows: the first solve only has to get the albedo close (its final decimals are redone), so
    # it stops early, with the quadratic prior (one factorisation per channel serves every target, no
    # majorise-minimise steps) and without the final float64 x-step. Measured on the dots bench scene: first solve
    # 25.5 -> 11.2 s, the stage 46 -> 33 s, envmap SSIM 0.597 -> 0.601 (bench/results.md)
    first = (dataclasses.replace(setup, tol=max(setup.tol, BOUNCE_FIRST_TOL), prior="smooth", polish=False)
             if refit_next else setup)
    stride = params.first_solve_stride if refit_next and L >= 2 and setup.lp == 0 else 1
    subs = subsample(cams, stride) if stride > 1 else None
    if subs is not None and sum(s.size for s in subs) < max(64, comp.texel_index.size):
        stride, subs = 1, None  # too few pixels left to fit: every pixel
    if subs is not None:
        res, auto, first_pixels = solve_subsampled(cams, subs, grid, comp.texel_index, first, sigma)
    else:
        res, auto = solve([c["rho0"] for c in cams], first)
        first_pixels = sum(int(c["rows"].size) for c in cams)
    # the support's light on the object was gathered at a guessed albedo: redo it from the estimate, solve again
    refits: list[dict] = []
    first_info = {"sweeps": int(res.iterations), "seconds": round(time.perf_counter() - t0, 3),
                  "objective": float(np.sum(res.objective)), "prior": first.prior, "tol": first.tol,
                  "pixel_stride": stride, "pixels": first_pixels}
    n_refits = params.bounce_refits if refit_next else 0
    loose = first is not setup  # res comes from a solve stopped early (a refit was to follow)
    level, search = None, None
    uniform = any(c.get("groups") is not None for c in cams)
    fit = params.bounce_level == "fit" or (params.bounce_level == "auto" and uniform)
    if n_refits and fit and not any(c["fixed"].any() for c in cams):
        level, search = fit_bounce_level(cams, comp, res, params, lambda: solve(res.rho, first)[0])
    for i in range(n_refits):
        t1 = time.perf_counter()
        more = refit_bounce(cams, comp, res, params, level)
        for r in more:
            r["seconds"] = round(time.perf_counter() - t1, 3)
            r["first_solve"] = first_info
            if search is not None:
                r["level_search"] = search
        if not more:
            break
        # every solve but the last one stops early too: another refit redoes its final decimals
        step = first if i < n_refits - 1 else setup
        res, auto = solve(res.rho, step)
        loose = step is not setup
        for r in more:
            r["objective_after"] = float(np.sum(res.objective))
        refits += more
    if loose and not res.diverged:
        # the last solve stopped early for a refit that found no cell to redo: finish it at the requested tol
        res, auto = solve(res.rho, setup)
    return res, auto, refits


def fit_bounce_level(cams: list[dict], comp, res, params: SolveParams, solve) -> tuple[float | None, dict | None]:
    """The support's mean albedo for the refitted interreflections where no pixel's albedo is known.

    The joint model ``y = rho A' x`` leaves one scale free (c rho, x / c fit alike), except in the light the
    support throws onto the object, which grows with the support's albedo itself; at the transport's guess (0.5)
    a brighter support's missing bounce light on the object's sides was made up by the low sky (bench/results.md,
    session 50). So each level of BOUNCE_LEVELS is tried (the refit at it, then ``solve()``: the joint solve
    from the first solve's albedo, stopped early as that one) from the middle downhill, and the minimum of the
    parabola through the lowest and its neighbours is taken (:func:`downhill_minimum`). Returns (level, record)
    or (None, None) when there is nothing to refit."""
    t0 = time.perf_counter()
    levels = list(BOUNCE_LEVELS)
    tried: dict[float, float] = {}

    def objective(lv: float) -> float | None:
        if lv not in tried:
            if not refit_bounce(cams, comp, res, params, lv):
                return None
            tried[lv] = float(np.sum(solve().objective))
        return tried[lv]

    if objective(levels[len(levels) // 2]) is None:
        return None, None
    level = downhill_minimum(levels, objective, tried)
    return level, {"levels": {f"{k:g}": round(v, 4) for k, v in sorted(tried.items())}, "chosen": round(level, 4),
                   "seconds": round(time.perf_counter() - t0, 3)}


def downhill_minimum(levels: list[float], objective, tried: dict[float, float]) -> float:
    """The minimiser of ``objective`` over the sorted grid ``levels`` refined by a parabola: from the values in
    ``tried`` (level -> objective; at least one, updated as more are evaluated), evaluate the untried neighbours of
    the lowest so far until it has both (or is at an end), then return the vertex of the parabola through it and
    its neighbours, clipped to their bracket; at an end, of the parabola through the three end levels, clipped to
    the end's interval. ``levels``: at least three."""
    while True:
        j = levels.index(min(tried, key=tried.get))
        nxt = [levels[i] for i in (j - 1, j + 1) if 0 <= i < len(levels) and levels[i] not in tried]
        if not nxt:
            break
        objective(nxt[0])
    j = levels.index(min(tried, key=tried.get))
    k = min(max(j, 1), len(levels) - 2)  # the middle of the three levels the parabola goes through
    for i in (k - 1, k, k + 1):
        if levels[i] not in tried:
            objective(levels[i])
    (a, fa), (b, fb), (c, fc) = [(levels[i], tried[levels[i]]) for i in (k - 1, k, k + 1)]
    lo, hi = (a, c) if j == k else ((a, b) if j < k else (b, c))
    den = (b - a) * (fb - fc) - (b - c) * (fb - fa)
    if den >= 0:  # not convex (a < b < c: convex is den < 0): the lowest level tried
        return float(levels[j])
    v = b - 0.5 * ((b - a) ** 2 * (fb - fc) - (b - c) ** 2 * (fb - fa)) / den
    return float(np.clip(v, lo, hi))


def subsample(cams: list[dict], stride: int) -> list[np.ndarray]:
    """Per camera, the positions (into its rows) of one pixel in ``stride`` x ``stride`` of the image grid, and of
    every pixel of known albedo."""
    subs = []
    for c in cams:
        pix = c["tr"].pixel_index[c["rows"]]
        w = c["tr"].image_shape[1]
        subs.append(np.flatnonzero((((pix // w) % stride == 0) & ((pix % w) % stride == 0)) | c["fixed"]))
    return subs


def solve_subsampled(cams: list[dict], subs: list[np.ndarray], grid: EnvGrid, texel_index: np.ndarray, setup,
                      sigma):
    """The joint solve on the rows ``subs`` of each camera (:func:`subsample`), then every pixel's albedo at its
    envmaps (:func:`objcam.solvers.joint.albedo_at`, the exact rho-step when lp = 0). Returns (result with rho for
    all rows, auto, pixels fitted)."""
    blocks = [(c["A"][s], c["Y"][s], c["tr"].pixel_index[c["rows"]][s], c["tr"].image_shape, c["rho0"][s],
               c["fixed"][s], None if c.get("groups") is None else c["groups"][s]) for c, s in zip(cams, subs)]
    res, auto = solve_joint_auto(blocks, grid, texel_index, setup, sigma=sigma)
    rho = [albedo_at(c["A"], c["Y"], res.x, c["rho0"], c["fixed"]) for c in cams]
    # a uniform surface's pixels take the one value the subsample fitted (objcam.solvers.joint.groups)
    set_values(rho, [c.get("groups") for c in cams], values_of(res.rho, [b[6] for b in blocks]))
    return dataclasses.replace(res, rho=rho), auto, sum(int(s.size) for s in subs)


def refit_bounce(cams: list[dict], comp, res, params: SolveParams, level: float | None = None) -> list[dict]:
    """Redo the interreflections of each camera's A' (in place) with the support's cells at the albedo the joint
    solve estimated over them (objcam.transport.gather.bounce_delta); returns one summary per camera changed
    (empty: nothing to redo, e.g. a direct-light A, the path-traced correction, or no cell seen). ``level``: where
    no pixel's albedo is known, the mean albedo the support's seen cells are given (:func:`fit_bounce_level`);
    None: the transport's guess."""
    if params.bounce_refits <= 0 or params.method != "exact" or res.diverged:
        return []
    out = []
    for p, c in enumerate(cams):
        tr = c["tr"]
        parts = tr.bounce_parts()
        if parts is None:
            continue
        # the joint albedo is known only up to one scale; the pixels of known albedo (the object, say) fix it for
        # the bounce, else its mean over the support stays at the transport's guess
        rows = c["rows"]
        rho = res.rho[p].mean(axis=1)
        known = ~tr.unknown_albedo[rows] & (rho > 0)
        if known.sum() >= 16:
            k = float(np.median(tr.albedo[rows][known].mean(axis=1) / rho[known]))
            how = f"median known/estimated albedo over {int(known.sum())} pixels"
        else:
            pn = parts["pixel_node"][rows]
            on = (pn >= 0) & tr.unknown_albedo[rows]
            guess = float(np.mean(parts["node_rho"][pn[on]].mean(axis=1))) if on.any() else 0.0
            target = guess if level is None else float(level)
            k = target / float(np.mean(rho[on])) if on.any() and np.mean(rho[on]) > 0 else 1.0
            how = ("mean over the support kept at the transport's guess" if level is None
                   else f"mean over the support at {target:.3g}, the level the joint objective chose")
        dA, info = bounce_delta(parts, k * rho, rows)
        if dA is None:
            continue
        info.update(albedo_scale=k, albedo_scale_from=how)
        # A' = A / rho: the transport renders unknown albedo as 1, known pixels carry theirs
        alb = tr.albedo[rows].mean(axis=1)
        dA = dA / np.where(alb > 0, alb, 1.0)[:, None]
        own = np.asarray(tr.texel_index)
        # the delta is from the transport's guess: apply it to the A' as built, not to a previous refit's
        base = c.setdefault("A_built", c["A"].copy())
        if own.size == comp.texel_index.size and np.array_equal(own, comp.texel_index):
            c["A"] = np.ascontiguousarray(base + dA, dtype=np.float32)
        else:
            c["A"] = base.copy()
            c["A"][:, np.searchsorted(comp.texel_index, own)] += dA
        rel = float(np.linalg.norm(dA) / max(np.linalg.norm(c["A"]), 1e-30))
        out.append({"camera": p, **info, "relative_change_of_A": rel,
                    "objective_before": float(np.sum(res.objective))})
    return out

