"""``transport.env_height=auto``: the finest envmap height the capture's data supports (issue 26).

The rule, a coarse-to-fine test on the photo itself (no ground truth): A is built at each candidate height in turn
(32, 64, 128 rows by default, each capped by :mod:`objcam.transport.budget`), and each target is fitted at every
built height with the quadratic prior at its noise rule (ls = LS_NOISE_FACTOR sigma^2, the solve's rule, times
``height_factor`` so every height carries the same continuous prior), unconstrained (a linear solve: its residual
and its hat matrix are exact and cheap). The finer height is taken when it explains the photo better than the
coarser one by more than its added freedom to fit noise. "The coarser one" is the finer grid fitted *blind*
inside the coarse texels (:func:`blind_transport`: every fine column its coarse parent's over k^2, k the height
ratio), not the coarse grid itself: the two fits then carry the same prior on the same grid, so the test sees what
the finer transport adds, not what the prior does to a jump at one height and at the other. (Against the coarse
fit, the (H/32)^4 prior priced the coarse grid's own jumps k times higher on the finer grid: forest and city at
0.1% noise gained -264 and -560 noise variances at 32 -> 64, and 3,136 and 4,087 over the blind fit;
bench/results.md, issue 26 session 20.) On a transport that holds nothing finer the two fits are one: gain 0.

    gain = (RSS_blind - RSS_fine) / s^2   >   max(dnu, 0) + Z sqrt(2 max(dnu, 1)),   dnu = nu_fine - nu_blind

with ``nu = 2 tr(H) - tr(H^2)`` the noise a linear smoother with hat matrix H absorbs (E[RSS] = sigma^2 (n - nu)
plus the bias: so under the hypothesis that the finer grid holds nothing the coarse one lacks, the gain is a
chi-square-like variable of mean ~delta nu and variance ~2 delta nu), ``s^2`` the larger of the stated noise
variance and the fine fit's residual variance (model error neither grid can fit is not taken for detail), and
``Z = 3`` (a one-sided 3-sigma test: about 1 in 1,000 captures whose data hold no finer light would be given the
finer grid). Z is a significance level fixed before any bench run, not fitted to a scene. The test walks up
while it passes and stops at the first height that does not; the capture takes the finest height any of its
targets supports (one grid for all cameras).

What it does not see: model error the finer grid *can* fit (an interreflection the direct model lacks, say) counts
as detail; and it tests linear fits, while the default solve is the edge prior with x >= 0.
The quadratic prior times height_factor is the same prior at every height only for smooth light: its cost of an
edge grows ~H and of a sub-texel source ~H^4 (bench/results.md, "Issue 26, session 20: why the coarse-to-fine test
rejects 128 x 256 on city"). That is why each step's baseline is the blind fit on the finer grid (same prior on
both sides) rather than the coarse fit, which kept city at 0.1% on 32 rows where 128 x 256 scores 0.031 higher.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

Z = 3.0  # one-sided significance of the test, in standard deviations of the null gain (module docstring)


@dataclass
class LevelFit:
    """One target's quadratic-prior fit at one height."""

    height: int
    rss: float  # sum of squared residuals over the fitted pixel values (absolute radiance^2)
    nu: float  # 2 tr(H) - tr(H^2), summed over the three colour columns
    dof: float  # tr(H), summed over the colour columns (the fit's effective degrees of freedom)
    values: int  # fitted pixel values (pixels x 3)


def _factor(Q: np.ndarray) -> np.ndarray:
    """Q's lower Cholesky factor, in place: Q (N, N) symmetric, C-ordered; returns the factor as a Fortran-ordered
    view of Q's memory (a symmetric C-ordered array is its own transpose in Fortran order)."""
    from scipy.linalg import lapack

    L, info = lapack.dpotrf(Q.T, lower=1, overwrite_a=1, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"the quadratic prior's Q is not positive definite (potrf info={info})")
    return L


def _hat_traces(L: np.ndarray, R) -> tuple[float, float]:
    """(tr(H), tr(H^2)) of the hat matrix H = A Q^-1 A^T, Q = G + R = L L^T (L: (N, N) float64 lower factor from
    :func:`_factor`, **overwritten** by Q^-1), R = ls D^T D + lr I sparse. Q^-1 G = I - X with X = Q^-1 R, so
    tr(H) = N - tr(X) and tr(H^2) = N - 2 tr(X) + tr(X^2): from Q^-1 (LAPACK potri, 2 N^3 / 3 flops) and products
    with the sparse R (a few N^2), in place. Forming Q^-1 G by N pairs of triangular solves took 2 N^3 flops and a
    second and third N x N array (128 x 256: 2.2 GB each)."""
    from scipy.linalg import lapack

    from objcam.solvers.regularization import _mirror_lower

    n = L.shape[0]
    S, info = lapack.dpotri(L, lower=1, overwrite_c=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"potri failed (info={info})")
    step = max(1, (64 << 20) // (8 * n))  # rows per band (64 MB)
    _mirror_lower(S, step)  # Q^-1 whole (potri fills the lower triangle)
    R = sp.csr_matrix(R)
    Rc = R.tocoo()
    tr_x = float(np.dot(Rc.data, S[Rc.row, Rc.col]))  # tr(Q^-1 R) = sum_ij (Q^-1)_ij R_ji, both symmetric
    tr_x2 = 0.0
    for r0 in range(0, n, step):  # tr(X^2) = sum_ij X_ij (X^T)_ij, X^T = R Q^-1: a band of rows at a time
        band = np.ascontiguousarray(S[r0 : r0 + step])
        x = (R @ band.T).T  # X[band, :] = Q^-1[band, :] R = (R Q^-1[:, band])^T
        xt = R[r0 : r0 + step] @ S  # (X^T)[band, :] = R[band, :] Q^-1
        tr_x2 += float(np.sum(x * xt))
    return n - tr_x, n - 2.0 * tr_x + tr_x2


def blind_transport(coarse, fine):
    """``fine`` (objcam.transport.storage.Transport) made blind inside ``coarse``'s texels: each fine column is its
    parent's column over k^2 (k = fine.env_height / coarse.env_height; a parent holds k^2 children, so a coarse map
    upsampled gives the coarse image), its Gram the parent's entries over k^4 (no new product). A fine texel whose
    parent the coarse grid does not keep sees nothing. Both must share their pixels (one camera)."""
    from dataclasses import replace

    if not np.array_equal(coarse.pixel_index, fine.pixel_index):
        raise ValueError("blind_transport: the two transports must keep the same pixels (one camera)")
    k = fine.env_height // coarse.env_height
    if k < 2 or fine.env_height != k * coarse.env_height:
        raise ValueError(f"blind_transport: {fine.env_height} rows is not a multiple of {coarse.env_height}")
    r, c = np.divmod(fine.texel_index, fine.grid.width)
    parent = (r // k) * coarse.grid.width + c // k
    pos = np.searchsorted(coarse.texel_index, parent).clip(0, coarse.n_texels - 1)
    sees = coarse.texel_index[pos] == parent
    A = coarse.A[:, :, pos] * np.float32(1.0 / k**2)
    A[:, :, ~sees] = 0
    G = coarse.gram()[:, pos][:, :, pos] / float(k**4)  # (C, N_fine, N_fine) float64
    G[:, ~sees] = 0
    G[:, :, ~sees] = 0
    out = replace(fine, A=A, folder=None)
    out._gram = G
    return out


def fit_level(A: np.ndarray, G: np.ndarray, D, y: np.ndarray, sigma_rel: float, height: int,
              lr_rel: float | None = None) -> LevelFit:
    """The quadratic-prior fit of y at one height.

    A: (C, M, N) float32 (C = 1: one grey A for the three colour columns; 3: one per channel); G: (C, N, N) the
    Gram matrices of exactly these rows; D: the difference operator of A's kept texels; y: (M, 3) pixel values;
    sigma_rel: relative noise per fitted pixel value (noise_sigma's convention). The prior: ls_rel =
    LS_NOISE_FACTOR sigma_rel^2 within LS_RANGE, times height_factor(height), and the solve's default ridge."""
    from objcam.solvers.plan.defaults import LS_NOISE_FACTOR, LS_RANGE
    from objcam.solvers.plan.rules import height_factor
    from objcam.solvers.regularization import DEFAULT_LR_REL, absolute_weights, regularized_gram

    lr_rel = DEFAULT_LR_REL if lr_rel is None else lr_rel
    ls_rel = float(np.clip(LS_NOISE_FACTOR * sigma_rel**2, *LS_RANGE)) * height_factor(height)
    rss = nu = dof = 0.0
    for c in range(A.shape[0]):
        cols = slice(None) if A.shape[0] == 1 else slice(c, c + 1)
        yc = np.asarray(y[:, cols], np.float64)
        ls, lr = absolute_weights(G[c], ls_rel, lr_rel)
        L = _factor(regularized_gram(G[c], D, ls, lr))  # one N x N array: Q, its factor, then Q^-1
        x = sla.cho_solve((L, True), A[c].T.astype(np.float64) @ yc, check_finite=False)
        rss += float(np.sum((yc - A[c].astype(np.float64) @ x) ** 2))
        R = lr * sp.identity(L.shape[0], format="csr") + (ls * (D.T @ D) if D is not None and ls > 0 else 0)
        t1, t2 = _hat_traces(L, R)
        k = yc.shape[1]  # colour columns sharing this A
        nu += k * (2 * t1 - t2)
        dof += k * t1
    return LevelFit(int(height), rss, nu, dof, int(y.size))


def compare(coarse: LevelFit, fine: LevelFit, sigma_abs: float, z: float = Z) -> dict:
    """The test of the module docstring: does ``fine`` explain the photo better than ``coarse`` by more than its
    added freedom? Returns {"supported", "gain", "added_nu", "threshold", "noise_abs", "residual_noise_abs"}
    (gain and threshold in units of s^2, the noise variance the test used)."""
    res_var = fine.rss / max(fine.values - fine.nu, 1.0)
    s2 = max(float(sigma_abs) ** 2, res_var)
    added = fine.nu - coarse.nu
    gain = (coarse.rss - fine.rss) / s2 if s2 > 0 else float("inf")
    # a finer fit with fewer effective dof (its prior, scaled by height_factor, can be the stronger) must still
    # explain the photo better, by the same margin: never chosen for fitting worse than expected
    threshold = max(added, 0.0) + z * np.sqrt(2.0 * max(added, 1.0))
    return {"supported": bool(gain > threshold), "gain": float(gain), "added_nu": float(added),
            "threshold": float(threshold), "noise_abs": float(sigma_abs), "residual_noise_abs": float(np.sqrt(res_var))}


def target_fit(tr, image: np.ndarray, valid: np.ndarray, sigma_rel: float) -> LevelFit:
    """fit_level for one target on one transport (objcam.transport.storage.Transport): the pooled target image
    (H', W', 3) and its valid mask (H', W') at A's kept pixels, non-finite values left out."""
    from objcam.solvers.regularization import difference_operator, gram
    from objcam.threads import single_blas_thread

    y = tr.pixels_of(image).astype(np.float64)
    use = tr.pixels_of(valid[..., None]).ravel().astype(bool) & np.isfinite(y).all(axis=1)
    A = tr.A if use.all() else tr.A[:, use]
    G = tr.gram() if use.all() else np.stack([gram(A[c]) for c in range(A.shape[0])])
    D = difference_operator(tr.grid, tr.texel_index)
    with single_blas_thread():  # factorisations: one BLAS thread is faster on this machine (objcam.threads)
        return fit_level(A, G, D, y[use], sigma_rel, tr.env_height)


def pooled_target(target, folder, tr) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(pooled image (H', W', 3), its valid mask (H', W'), relative noise per fitted pixel value, absolute noise)
    of one capture target on a transport's pixels: the stated noise_sigma over the pooling, else estimated from
    the image (1% when it cannot be)."""
    from objcam.transport.auto import absolute_noise, estimate_relative_noise
    from objcam.transport.pixels import pool_target

    img, ok = pool_target(target.load_image(folder), target.load_valid(folder), tr.downsample)
    rel = float(target.noise_sigma / tr.downsample if target.noise_sigma is not None
                else (estimate_relative_noise(img, ok) or 0.01))
    return img, ok, rel, absolute_noise(tr.pixels_of(img)[tr.pixels_of(ok[..., None]).ravel()], rel)


def walk(fits: dict[int, LevelFit], sigma_abs: float, z: float = Z,
         blind: dict[int, LevelFit] | None = None) -> tuple[int, list[dict]]:
    """(the chosen height, one record per comparison made): up from the coarsest fitted height while the next one
    is supported. ``blind[hi]``: the fit of height hi blind inside the next coarser height's texels
    (:func:`blind_transport`), the baseline of that step (module docstring); where absent, the coarser fit is."""
    heights = sorted(fits)
    chosen, steps = heights[0], []
    for lo, hi in zip(heights, heights[1:]):
        base = (blind or {}).get(hi, fits[lo])
        rec = {"from": lo, "to": hi, "against": "blind" if base is not fits[lo] else "coarse"} \
            | compare(base, fits[hi], sigma_abs, z)
        steps.append(rec)
        if not rec["supported"]:
            break
        chosen = hi
    return chosen, steps


def affordable(heights, estimates, max_seconds: float, memory: int | None = None) -> tuple[list[int], dict[int, str]]:
    """(the candidate heights the budget allows, ascending; {refused height: why}): a height is refused when
    any camera's estimate (``estimates(height)``: objcam.transport.budget.estimate per camera, as the transport
    stage plans its build) passes the machine's memory or the build's planned seconds (A, Gram, the exact solves
    and their verdicts; budget.plan) pass ``max_seconds``. Heights above a refused one are refused too."""
    from objcam.errors import StageError
    from objcam.transport import budget

    ok, refused = [], {}
    for h in sorted(set(int(v) for v in heights)):
        if refused:
            refused[h] = f"above the refused {min(refused)}"
            continue
        ests = estimates(h)
        try:
            for est in ests:
                budget.check(est, None, memory)
        except StageError as e:
            refused[h] = str(e).split(" -- fix:")[0].strip()
            continue
        secs = budget.plan(ests)["seconds"]
        if secs > max_seconds:
            refused[h] = (f"planned {secs:,.0f} s (A, Gram, exact solves and verdicts; objcam.transport.budget) > "
                          f"transport.env_height_max_seconds {max_seconds:g}")
            continue
        ok.append(h)
    return ok, refused


def choose_height(out, params, art, groups: list[list], estimates, build, toml=None) -> tuple[int, dict]:
    """Run the rule for the transport stage: A built at each affordable candidate height into ``out``/h<H>
    (``build(height, folder)`` -> (per-camera metrics, {target: "cam<i>"}); ``estimates(height)`` -> budget
    estimates per camera), the targets fitted, the walk stopped at the first height no target supports. The chosen
    height's cameras are moved to ``out``/cam<i> and the other heights' A deleted.

    Returns (height, record): record = {"height", "reason", "candidates", "refused", "targets": {name: {"height",
    "noise_rel", "steps"}}, "z", "seconds_per_height", "_built": the chosen build's (metrics, mapping)}."""
    import os
    import shutil
    import time

    from objcam.errors import StageError
    from objcam.transport.storage import load_group

    c0 = time.process_time()
    heights, refused = affordable(params.env_height_candidates, estimates, params.env_height_max_seconds)
    if not heights:
        why = "; ".join(f"{h}: {r}" for h, r in refused.items())
        raise StageError(f"transport.env_height=auto: no candidate height fits ({why})",
                         toml,
                         "lower transport.env_height_candidates or raise transport.env_height_max_seconds")
    built: dict[int, tuple] = {}
    fits: dict[str, dict[int, LevelFit]] = {}
    noise: dict[str, tuple[float, float]] = {}
    seconds: dict[int, float] = {}
    blind: dict[str, dict[int, LevelFit]] = {}
    targets = [t for g in groups for t in g]
    images = {}
    coarser: dict = {}  # the previous height's transport per target: the blind fit's parent grid
    for h in heights:
        t0 = time.perf_counter()
        folder = out / f"h{h}"
        shutil.rmtree(folder, ignore_errors=True)
        built[h] = build(h, folder)
        loaded: dict = {}  # one A per camera, shared by its targets
        this: dict = {}
        for t in targets:
            sub = built[h][1][t.name]
            tr = loaded[sub] if sub in loaded else loaded.setdefault(sub, load_group(folder / sub))
            if t.name not in images:  # the pooled photo and its noise, once per target
                img, ok, rel, sigma_abs = pooled_target(t, art.folder, tr)
                images[t.name] = (img, ok)
                noise[t.name] = (rel, sigma_abs)
            fits.setdefault(t.name, {})[h] = target_fit(tr, *images[t.name], noise[t.name][0])
            if t.name in coarser:  # the same grid blind inside the coarser texels: the step's baseline
                blind.setdefault(t.name, {})[h] = target_fit(blind_transport(coarser[t.name], tr),
                                                              *images[t.name], noise[t.name][0])
            this[t.name] = tr
        coarser = this
        del loaded, tr, this
        seconds[h] = round(time.perf_counter() - t0, 3)
        walked = {n: walk(f, noise[n][1], blind=blind.get(n)) for n, f in fits.items()}
        if len(fits[targets[0].name]) > 1 and all(c < h for c, _ in walked.values()):
            break  # no target supports this height: finer ones are not built
    chosen = max(c for c, _ in walked.values())
    for h in list(built):
        if h != chosen:
            shutil.rmtree(out / f"h{h}", ignore_errors=True)
    per_cam, mapping = built[chosen]
    for sub in sorted(set(mapping.values())):
        shutil.rmtree(out / sub, ignore_errors=True)
        os.replace(out / f"h{chosen}" / sub, out / sub)
    shutil.rmtree(out / f"h{chosen}", ignore_errors=True)
    per_target = {n: {"height": c, "noise_rel": noise[n][0], "steps": steps} for n, (c, steps) in walked.items()}
    why = [f"{n}: " + ", ".join(f"{s['from']}->{s['to']} gain over the blind fit {s['gain']:,.0f} "
                                f"{'>' if s['supported'] else '<='} {s['threshold']:,.0f}" for s in r["steps"])
           for n, r in per_target.items()]
    tried = [h for h in heights if h in built]
    reason = (f"the finest height a target supports among {tried}" + (f" ({'; '.join(why)})" if why else "")
              + (f"; refused {', '.join(f'{h} ({r})' for h, r in refused.items())}" if refused else ""))
    return chosen, {"height": chosen, "reason": reason, "candidates": list(params.env_height_candidates),
                    "built": tried, "refused": {str(h): r for h, r in refused.items()}, "z": Z,
                    "targets": per_target, "seconds_per_height": {str(h): s for h, s in seconds.items()},
                    "cpu_seconds": round(time.process_time() - c0, 3),  # this process, every build and fit
                    "_built": (per_cam, mapping)}
