"""The verdict: how far one recovered envmap can be trusted, green / yellow / red, from what the data say.

No ground truth is used: every measure comes from the photo, the model and the solve.

* ``chi2``: the residual per fitted pixel value over the photo's noise (``noise_sigma`` per photo pixel over the
  pooling, else the photo's own, auto.estimate_pixel_noise: the median |Laplacian|, which edges and texture do not
  inflate; the prior's mean-|Laplacian| reading, rules.fitted_noise, counts them and on photographed captures
  reads 1.6-3x more: bench/results.md, session 54), squared and averaged. ~1 when the model explains the photo to its
  noise; far above it, the photo holds light or geometry the model lacks (interreflections, a wrong mesh, a
  saturated area, a hot pixel). ``residual_fraction``: the same residual over the photo (root sums of squares):
  how much of the light the model leaves unexplained. chi2 says whether a misfit is real, the fraction whether it
  is large; red needs both (chi2 grows as 1 + (misfit / noise)^2: the same misfit of a fiftieth of the light is
  chi2 ~17 at 0.5% noise and ~2 at 2%).
* ``uncertain_area``: the share of the sky (solid angle above the horizon) whose texels' uncertainty exceeds
  their recovered value. Uncertainty per texel: ``sigma sqrt(diag(Q^-1))`` with ``Q = A^T A + ls D^T D + lr I``
  at the quadratic prior's noise rule (ls = LS_NOISE_FACTOR sigma^2): the posterior spread of the recovered
  radiance under the stated noise and a smoothness prior. Where it exceeds the value, the priors, not the photo,
  drew that part of the map. ``uncertain_visible_area``: the same where the spread also exceeds a fiftieth of the
  map's 99th-percentile brightness (the tonemap's white): the undetermined part a viewer sees (a dark, flat,
  undetermined background that the prior draws flat is not counted); ``uncertain_visible_energy`` its share of
  the map's light (red needs both, or the map's brightest light in a poorly seen direction, ``brightest_seen``:
  a dark room's undetermined dim walls hold a few thousandths of the light beside lamps the photo sees well; a
  camera that sees nothing leaves the rest of its sky undetermined and its light where it barely looks).
* ``dark_sky_area``: the share of the solved sky (solid angle above the horizon) that the solve held at the
  radiance >= 0 bound (luminance at most ``VERDICT_DARK_LEVEL`` x the sky's 99th percentile). No real sky is black
  over an area; a black region is the clipped negative lobe of a fit to what the model cannot express, e.g. the
  sharp shadows of a light smaller than a texel, which box texels can only sharpen by a dark ring around it.
  ``dark_sky_light``: the light that black would hold at the sky's level (:func:`black_light`) as a share of the
  map's (red needs it above a tenth: black walls in a dark room are not a black patch in a sunlit sky, or the
  black over more than half of the sky: then the map shows the lights, not the place).
  ``dark_sky_area_solved`` / ``dark_sky_light_solved``: the same of the edge solve's map where solve.sky_profile
  then gave the sky as its row means (which fill the black but not what the model missed there); the grade takes
  the larger.
* ``below_horizon_energy``: the share of the map's energy (luminance x solid angle) the solve put below the
  horizon, seen only past the support's edge; ``brightest_elevation_deg`` and ``brightest_seen``: the brightest
  source's elevation and its column norm over the median column norm (how strongly the photo sees that
  direction), both over the source's region, weighted by light (:func:`brightest_source`).
* ``resolved_values`` and ``resolution_deg``: how many independent values of the sky above the horizon the photo
  determines (the trace of the model resolution matrix of the same posterior, :func:`resolved_values`) and the
  angle they resolve (the sky's solid angle shared among them). A property of the photo, the geometry and the
  noise, not of the map: above ``VERDICT_RESOLUTION_YELLOW`` (30 deg) the map's finer detail, a canopy's texture
  or a lamp's sharpness, is the prior's (yellow; it cannot tell a blurred canopy from a lamp the prior happens to
  draw sharp, so never red).
* ``pixels_excluded``: the share of A's pixels the solve could not use (saturated, invalid, hot);
  ``pixels_rejected``: the share of the usable ones it dropped as outliers (objcam.solvers.outliers). chi2 is over
  the pixels it fitted.
* the transport's ``auto`` decision margin (objcam.transport.auto) when it left interreflections out.
* ``object_albedo_unknown``: the share of the object's pixels (object_fraction >= 1/2) whose albedo the solve
  estimated per pixel (0 where capture.toml declares the object "uniform": one value for all of it, which kept
  the low sky near the level a given albedo gives, session 50). Where it is most of them, the low sky comes out
  too bright: measured on photographed captures with every albedo unknown, the 0-10 deg band at 4-10x the
  truth's energy (4.6-6x on three of the sweep's nine twins once the joint solve converged, session 51), 2-4x
  with the object's albedo given, and the object's albedo estimated low (bench/results.md, session 49). Light a
  few degrees up reaches the object's sides and barely the plane, so that band's level follows the object's albedo
  against the support's (given 25% low or 33% high it moved 2-3x -> 3-4.5x and 0.04-0.09x). Not a spread this
  posterior misses by holding the albedo fixed: eliminating each pixel's albedo exactly widens the low sky's
  spread by ~10% only; but the spread is compared with the estimate, and an estimate several times too bright
  looks determined. Yellow, with the fix.
* ``sky_profile_area``: the share of the sky the map gives as one value per elevation row
  (objcam.solvers.skyprofile): its azimuthal detail is the prior's, not the photo's (yellow). Those texels'
  uncertainty is that of their row's value in the map's own model (:func:`row_mean_spread`).
  ``sky_profile_by_misfit``: the profile was told from the map only within the map's own misfit beyond the noise
  (its fit rose by more than a spread; the reason says so).

Thresholds (objcam.solvers.plan.defaults, ``VERDICT_*``) and how they were chosen: bench/results.md, issue 22.

Measured on the hard suite and not used, because none of them separates its SSIM < 0.4 maps from its good ones
(bench/results.md, sessions 15 and 18):
* a parametric bootstrap;
* a predicted SSIM from posterior samples ``x_hat + sigma L^-T z``, under the smoothness or the solve's own edge
  prior;
* the disagreement with the smoothness prior's solve;
* the residuals' spatial structure.
Those maps' error is the prior's bias where the photo is silent, and none of these statistics see it.
"""

from __future__ import annotations

import numpy as np

from objcam import solvers
from objcam.solvers.plan.defaults import (
    LS_NOISE_FACTOR,
    VERDICT_BELOW_RED,
    VERDICT_BELOW_YELLOW,
    VERDICT_CHI2_RED,
    VERDICT_CHI2_YELLOW,
    VERDICT_DARK_AREA_RED,
    VERDICT_DARK_LEVEL,
    VERDICT_DARK_YELLOW,
    VERDICT_EXCLUDED_YELLOW,
    VERDICT_LIGHT_RED,
    VERDICT_MARGIN_YELLOW,
    VERDICT_REJECTED_YELLOW,
    VERDICT_RESIDUAL_RED,
    VERDICT_RESOLUTION_YELLOW,
    VERDICT_SEEN_YELLOW,
    VERDICT_UNCERTAIN_RED,
    VERDICT_VISIBLE_FRACTION as VISIBLE_FRACTION,
    VERDICT_UNCERTAIN_YELLOW,
)
from objcam.solvers.plan.rules import fitted_noise, relative_column_norms
from objcam.solvers.plan.targets import TargetData, TargetSolution

GRADES = ("green", "yellow", "red")


def chi2_per_value(y: np.ndarray, fit: np.ndarray, sigma_rel: float) -> tuple[float, float]:
    """(chi-squared per pixel value, absolute sigma) of the fit (M, 3) to y (M, 3) at relative noise sigma_rel
    (over the median positive pixel value, as noise_sigma)."""
    from objcam.transport.auto import absolute_noise

    sigma_abs = absolute_noise(y, sigma_rel)
    return float(np.mean(((y - fit) / sigma_abs) ** 2)), sigma_abs


def residual_fraction(y: np.ndarray, fit: np.ndarray) -> float:
    """The share of the photo the fit leaves unexplained: ``||y - fit|| / ||y||`` over the fitted pixel values
    (M, 3) (0: a perfect fit; 1: the fit explains nothing; the noise alone gives about the relative noise). Unlike
    chi-squared it does not grow with the signal to noise ratio."""
    den = float(np.sum(np.square(y, dtype=np.float64)))
    return float(np.sqrt(np.sum(np.square(y - fit, dtype=np.float64)) / den)) if den > 0 else 0.0


#: Texels above which the verdict's Q is factorised in float32 on every core (objcam.analysis.inverse_diagonal):
#: float64 on one BLAS thread took 73 s of a 153 s solve stage at 128 x 256 (16,640 texels, quiet machine) and
#: 4 N x N float64 copies (8.9 GB). Float32 against float64 (bench/results.md, issue 26, session 19): at 128 x 256
#: (forest, 2.3% noise) 2.2e-5 relative at most; at 64 x 128 on the resolution bench's captures 1.3-2.0e-5 at 2%
#: noise but up to 8.2e-4 at 0.1% (a weaker prior, a worse-conditioned Q), no decision changed in any of them.
#: 64 x 128 (4,224 texels, ~2 s in float64) stays in float64; float32 from 128 x 256 on.
UNCERTAINTY_FLOAT64_MAX = 8192
_BAND_BYTES = 64 << 20  # float64 rows of the Gram read (and corrected) at a time


def data_gram(grams: np.ndarray, dropped: list[np.ndarray], dtype=np.float64,
              order: np.ndarray | None = None) -> np.ndarray:
    """(N, N) C-ordered ``dtype``: the channels' mean Gram matrix minus the dropped rows' own, ``mean_c (G_c -
    A_c[drop]^T A_c[drop])``, its rows and columns in ``order`` (a permutation of the N texels; None: as stored).
    ``grams``: (C, N, N) float64 (gram.npy, memory-mapped); ``dropped``: per channel the rows of A the solve did
    not fit (k, N) float64, or []. Built band by band in float64 and stored in ``dtype``: no N x N float64 copy
    besides the result (the Gram file's pages are the page cache's)."""
    c, n = grams.shape[0], grams.shape[-1]
    idx = np.arange(n) if order is None else np.asarray(order, dtype=np.int64)
    out = np.empty((n, n), dtype=dtype)
    drop = [a[:, idx] for a in dropped if a.shape[0]]
    step = max(1, _BAND_BYTES // (8 * n))
    for r0 in range(0, n, step):
        r1 = min(n, r0 + step)
        rows = slice(r0, r1) if order is None else idx[r0:r1]
        band = np.array(grams[0, rows], dtype=np.float64)
        for ch in range(1, c):
            band += grams[ch, rows]
        if order is not None:
            band = np.take(band, idx, axis=1)  # 3x faster than band[:, idx] at 16,640 columns
        if c > 1:
            band /= c
        for a in drop:
            band -= (a[:, r0:r1].T @ a) / c
        out[r0:r1] = band
    return out


def data_gram_diagonal(grams: np.ndarray, dropped: list[np.ndarray]) -> np.ndarray:
    """(N,) float64: the diagonal of :func:`data_gram` (the channels' mean Gram of the fitted pixels) without
    forming it: ``grams`` (C, N, N) and ``dropped`` as there."""
    return (sum(np.asarray(np.diagonal(grams[c]), np.float64) for c in range(grams.shape[0]))
            - sum(np.einsum("ij,ij->j", a, a) for a in dropped)) / grams.shape[0]


def _prior(grams: np.ndarray, dropped: list[np.ndarray], D, sigma_rel: float, lr_rel: float) -> tuple:
    """(diag(G) (N,), ls_abs, lr_abs, D^T D as COO with duplicates summed or None) of the verdict's posterior
    precision ``Q = G + ls D^T D + lr I`` (:func:`texel_uncertainty`)."""
    n = grams.shape[-1]
    diag = data_gram_diagonal(grams, dropped)
    scale = float(np.mean(diag)) if n else 0.0  # solvers.absolute_weights' unit: mean(diag(G))
    ls_abs, lr_abs = LS_NOISE_FACTOR * sigma_rel**2 * scale, max(lr_rel, 1e-6) * scale
    P = (D.T @ D).tocoo() if D is not None and ls_abs > 0 and D.shape[0] else None
    if P is not None:
        P.sum_duplicates()
    return diag, ls_abs, lr_abs, P


#: the resolution (:func:`resolved_values`) up to this many texels (32 x 64's 2,048; ~0.07 s at 1,088 on one
#: core): a finer grid (transport.env_height=auto) is one the coarse-to-fine test found the photo resolves, and
#: its dense solve would cost seconds (64 x 128: ~1.6 s)
RESOLUTION_MAX_TEXELS = 2304


def resolved_values(grams: np.ndarray, dropped: list[np.ndarray], D, sigma_rel: float, lr_rel: float,
                    up: np.ndarray) -> float | None:
    """How many independent values of the sky above the horizon the photo determines: the trace over the texels
    ``up`` (N,) bool of the model resolution matrix ``R = Q^-1 G`` of the verdict's posterior (G the data Gram
    matrix, :func:`data_gram`; Q as in :func:`texel_uncertainty`: with the smoothness prior at the noise rule and
    the ridge). R maps a true sky to what the quadratic solve recovers from its noise-free photo; its diagonal is
    the share of a texel's own value in the estimate there (1: resolved; near 0: drawn from its neighbours by the
    prior), so its trace counts the values the photo tells apart. None above RESOLUTION_MAX_TEXELS texels or
    without texels above the horizon. Call with one BLAS thread."""
    import scipy.linalg as sl

    n = grams.shape[-1]
    idx = np.flatnonzero(up)
    if n > RESOLUTION_MAX_TEXELS or idx.size == 0:
        return None
    G = data_gram(grams, dropped)
    _, ls_abs, lr_abs, P = _prior(grams, dropped, D, sigma_rel, lr_rel)
    Q = G.copy()
    if P is not None:
        Q[P.row, P.col] += ls_abs * P.data
    Q[np.diag_indices_from(Q)] += lr_abs
    fac = sl.cho_factor(Q, lower=True, overwrite_a=True, check_finite=False)
    X = sl.cho_solve(fac, G[:, idx], check_finite=False)  # (N, k): the columns idx of R
    return float(np.trace(X[idx]))


def row_mean_spread(grams: np.ndarray, dropped: list[np.ndarray], D, sigma_rel: float, sigma_abs: float,
                    lr_rel: float, rows: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """(N,): for each texel of ``sky`` (N,) bool, which the map gives as one value per row (its row's mean:
    objcam.solvers.skyprofile; ``rows`` (N,) lat-long rows), the posterior standard deviation of that value in
    the map's own model, the envmaps ``x = B z`` with one unknown per row's ``sky`` texels and one per other
    texel: ``sigma_abs sqrt(((B^T Q B)^-1)_rr)``, Q as in :func:`texel_uncertainty` (the same posterior, restricted
    to the envmaps the map claims, as the solves' merged bases restrict theirs); NaN elsewhere. ``B^T Q B`` is
    merged from the Gram file block by block (objcam.solvers.basis.merge_gram): no N x N array."""
    import scipy.linalg as sl
    import scipy.sparse as sp

    from objcam.solvers.basis import merge_gram

    n = grams.shape[-1]
    out = np.full(n, np.nan)
    if not sky.any():
        return out
    _, ls_abs, lr_abs, _ = _prior(grams, dropped, D, sigma_rel, lr_rel)
    r_of, r_idx = np.unique(rows[sky], return_inverse=True)
    col = np.empty(n, np.int64)
    col[sky] = r_idx.ravel()
    col[~sky] = r_of.size + np.arange(int((~sky).sum()))
    B = sp.csr_matrix((np.ones(n), (np.arange(n), col)), shape=(n, r_of.size + int((~sky).sum())))
    c = grams.shape[0]
    QB = sum(merge_gram(B, grams[ch]) for ch in range(c)) / c
    for a in dropped:
        ab = np.asarray((B.T @ a.T).T)  # (k, K): the dropped rows on the basis
        QB -= (ab.T @ ab) / c
    if D is not None and ls_abs > 0 and D.shape[0]:
        DB = sp.csr_matrix(D @ B)
        QB += ls_abs * (DB.T @ DB).toarray()
    QB += lr_abs * (B.T @ B).toarray()
    fac = sl.cho_factor(QB, lower=True, overwrite_a=True, check_finite=False)
    E = np.zeros((QB.shape[0], r_of.size))
    E[np.arange(r_of.size), np.arange(r_of.size)] = 1.0
    var = np.diag(sl.cho_solve(fac, E, check_finite=False)[: r_of.size])
    out[sky] = sigma_abs * np.sqrt(np.maximum(var, 0.0))[r_idx.ravel()]
    return out


def texel_uncertainty(grams: np.ndarray, dropped: list[np.ndarray], D, sigma_rel: float, sigma_abs: float,
                      lr_rel: float, above: np.ndarray | None = None, dtype=None) -> tuple[np.ndarray, dict]:
    """((N,) posterior standard deviation of each texel's radiance, {"precision", "exact_texels"}):
    ``sigma_abs sqrt(diag(Q^-1))``, ``Q = G + ls D^T D + lr I`` with G the data Gram matrix (:func:`data_gram` of
    ``grams`` and ``dropped``), ls = LS_NOISE_FACTOR sigma_rel^2 and lr relative to mean(diag(G)) (the smoothness
    prior included).

    ``above`` (N,): the values the caller compares the spread with. Where the lower bound ``sigma_abs /
    sqrt(Q_jj)`` (the spread were every other texel known: ``(Q^-1)_jj >= 1 / Q_jj``) already exceeds it, that
    bound is returned (the comparison's answer is exact) and the texel is ordered first; the rest are computed
    from the factor's trailing block (objcam.analysis.inverse_diagonal): N^3 / 3 + m^3 / 3 flops for m of them.
    ``dtype``: None for float32 on every core above UNCERTAINTY_FLOAT64_MAX texels, else float64 on one thread;
    Q is formed and factorised in place (one N x N array); a float32 Q that is not positive definite in float32
    is redone in float64."""
    from objcam.analysis import inverse_diagonal
    from objcam.threads import cores

    n = grams.shape[-1]
    diag, ls_abs, lr_abs, P = _prior(grams, dropped, D, sigma_rel, lr_rel)
    qdiag = diag + lr_abs
    if P is not None:
        qdiag += ls_abs * np.bincount(P.row[P.row == P.col], P.data[P.row == P.col], minlength=n)
    s = sigma_abs / np.sqrt(qdiag)  # lower bounds
    need = np.ones(n, bool) if above is None else ~(s > above)
    order = np.concatenate([np.flatnonzero(~need), np.flatnonzero(need)])
    m = int(need.sum())
    first = np.dtype(dtype or (np.float32 if n > UNCERTAINTY_FLOAT64_MAX else np.float64))
    info = {"precision": first.name, "exact_texels": m}
    if m == 0:
        return s, info
    inv = np.empty(n, np.int64)
    inv[order] = np.arange(n)
    for dt in dict.fromkeys([first, np.dtype(np.float64)]):
        Q = data_gram(grams, dropped, dt, None if m == n else order)
        if P is not None:  # a few entries per row: added in place, in Q's precision
            Q[inv[P.row], inv[P.col]] += ls_abs * P.data
        Q[np.diag_indices_from(Q)] += lr_abs
        try:
            var = inverse_diagonal(Q, overwrite=True, threads=cores() if dt == np.float32 else 1, last=m)
        except np.linalg.LinAlgError:
            if dt == np.float64:
                raise
            del Q
            continue
        s[order[n - m :]] = sigma_abs * np.sqrt(var)
        return s, info | {"precision": dt.name}
    raise AssertionError("unreachable")


def brightest_source(env: np.ndarray, mask: np.ndarray | None, tr, seen: np.ndarray) -> tuple[float, float]:
    """(the sine of the brightest source's elevation, how strongly the photo sees it) of the map ``env`` (H, W, 3)
    on A's grid, its solved texels ``mask`` (H, W) bool or None; ``seen`` (N,): A's texels' relative column norms
    (rules.relative_column_norms).

    A source is a region, not a texel: the texels at >= half the brightest one's luminance connected to it
    (objcam.metrics.brightest_region, as evaluate scores the brightest source), its elevation that of their
    light-weighted centre, how well it is seen their light-weighted mean of ``seen``. An extended bright area
    along the horizon (a sunlit facade) whose brightest texel happens to lie a row below it is above the horizon
    (held out courtyard_r60: its brightest texel 16.7 at -2.8 deg beside 16.2 at +2.8, the area's centre 7 deg
    up); a sun put below it is below."""
    from objcam.metrics import LUMA, brightest_region, region_centre

    region = brightest_region(env, mask)
    lum = np.asarray(env, np.float64).reshape(-1, 3)[tr.texel_index] @ np.asarray(LUMA)
    inside = np.zeros(lum.size, bool) if region is None else region.reshape(-1)[tr.texel_index]
    if not inside.any():  # no light, or none of the region's texels is one of A's: the brightest of A's texels
        jb = int(np.argmax(lum))
        return float(tr.directions[jb, 2]), float(seen[jb])
    w = np.clip(lum[inside], 0, None) * np.asarray(tr.solid_angle, np.float64)[inside]
    return float(region_centre(env, region)[2]), float(np.sum(w * seen[inside]) / max(float(w.sum()), 1e-300))


def assess(target, d: TargetData, sol: TargetSolution, lr_rel: float, full: bool = True) -> dict:
    """The verdict record of one target (solve.json's ``verdict``): ``grade``, ``reasons`` (one line each, the
    worst first) and the measures above; ``full`` False: without the posterior's (the uncertainty's and the
    resolution's), for a caller that compares fits only (solve.verdict=fit)."""
    tr, y = d.transport, d.y
    use = d.use if sol.rejected is None else d.use & ~sol.rejected  # the pixels the solve fitted
    env = sol.fine[0] if sol.fine is not None else sol.envmap  # A's own grid
    X = tr.x_from_envmap(env).astype(np.float64)
    fit = np.asarray(sol.prediction, np.float64).reshape(-1, 3)[tr.pixel_index][use]  # the solve's own model
    sigma_rel, noise_source = fitted_noise(target, d.pooled, d.pooled_ok, tr.downsample)
    lum = X.mean(axis=1)
    omega = tr.solid_angle.astype(np.float64)
    up = tr.directions[:, 2] > 0
    energy = np.clip(lum, 0, None) * omega
    total = max(float(energy.sum()), 1e-300)
    mask = sol.fine[1] if sol.fine is not None else sol.mask
    solved = np.ones(lum.size, bool) if mask is None else np.asarray(mask, bool).reshape(-1)[tr.texel_index]
    rec: dict = {"noise_per_fitted_pixel": sigma_rel, "noise_source": noise_source,
                 "pixels_excluded": float(1.0 - d.use.mean()),
                 "pixels_rejected": float(0.0 if sol.rejected is None else sol.rejected.sum() / max(d.use.sum(), 1)),
                 "below_horizon_energy": float(energy[~up].sum() / total),
                 "dark_sky_area": dark_sky_area(lum, omega, up & solved),
                 "dark_sky_light": black_light(lum, omega, dark_sky(lum, up & solved), up & solved),
                 "residual_fraction": residual_fraction(y[use], fit)}
    grams, nc = tr.gram(), tr.A.shape[0]  # (C, N, N), memory-mapped: read in bands, never copied whole
    dropped = [] if use.all() else [np.asarray(tr.A[c][~use], np.float64) for c in range(nc)]
    diag = data_gram_diagonal(grams, dropped)
    up_b, rec["brightest_seen"] = brightest_source(env, mask, tr, relative_column_norms(diag, tr.directions))
    rec["brightest_elevation_deg"] = float(np.degrees(np.arcsin(np.clip(up_b, -1, 1))))
    if sigma_rel:
        from objcam.transport.auto import absolute_noise, estimate_pixel_noise

        # the residual against the photo's noise; the posterior's measures below at the prior's reading
        chi_rel, _ = fitted_noise(target, d.pooled, d.pooled_ok, tr.downsample, estimator=estimate_pixel_noise)
        rec["chi2"], _ = chi2_per_value(y[use], fit, chi_rel or sigma_rel)
        sigma_abs = absolute_noise(y[use], sigma_rel)
        if chi_rel and chi_rel != sigma_rel:
            rec["photo_noise_per_fitted_pixel"] = chi_rel
    if sigma_rel and full:
        D = solvers.difference_operator(tr.grid, tr.texel_index)
        # what a viewer sees: texels whose spread exceeds both their value and a fiftieth of the map's
        # 99th-percentile brightness (the tonemap's white): a dark, uncertain but flat background passes
        white = float(np.percentile(lum[up], 99)) if up.any() else 0.0
        above = np.maximum(lum, VISIBLE_FRACTION * white)  # >= lum: a spread above it answers both tests
        s, how = texel_uncertainty(grams, dropped, D, sigma_rel, sigma_abs, lr_rel, above=above)
        rec["uncertainty_precision"], rec["uncertainty_exact_texels"] = how["precision"], how["exact_texels"]
        if sol.profile is not None and sol.profile.any():
            # texels the map gives as one value per row (objcam.solvers.skyprofile): the spread of that value in
            # the model the map claims, not one free texel's
            rows = tr.texel_index // tr.grid.width
            s = np.where(sol.profile, row_mean_spread(grams, dropped, D, sigma_rel, sigma_abs, lr_rel, rows,
                                                      sol.profile), s)
            rec["uncertainty_row_means"] = int(np.unique(rows[sol.profile]).size)
        unsure = s > lum
        sky = max(float(omega[up].sum()), 1e-300)
        values = resolved_values(grams, dropped, D, sigma_rel, lr_rel, up)
        if values is not None:  # the angular scale the photo resolves: the sky's solid angle shared among them
            rec["resolved_values"] = values
            rec["resolution_deg"] = float(np.degrees(np.sqrt(sky / max(values, 1e-12))))
        rec["uncertain_area"] = float(omega[unsure & up].sum() / sky)
        rec["uncertain_energy"] = float(energy[unsure].sum() / total)
        shown = s > above
        rec["uncertain_visible_area"] = float(omega[shown & up].sum() / sky)
        rec["uncertain_visible_energy"] = float(energy[shown & up].sum() / total)
    if sol.profile is not None and sol.profile.any():
        rec["sky_profile_area"] = float(omega[sol.profile & up].sum() / max(float(omega[up].sum()), 1e-300))
        test = sol.info.get("edges", {}).get("sky_profile", {})
        for key in ("dark_sky_area_solved", "dark_sky_light_solved"):
            if test.get(key) is not None:
                rec[key] = float(test[key])
        if "ss_profile_fitted" in test:  # taken within the map's own misfit beyond the noise, not within a spread
            rec["sky_profile_by_misfit"] = bool(test["ss_profile_fitted"] - test["ss_map"] > test["ss_spread"])
    on_object = np.asarray(tr.object_fraction) >= 0.5
    one_colour = "object" in (sol.info.get("albedo_uniform") or {})  # estimated as one value, not per pixel
    rec["object_albedo_unknown"] = (float(np.asarray(tr.unknown_albedo)[on_object].mean())
                                    if on_object.any() and not one_colour else 0.0)
    metrics = tr.attrs.get("metrics", {}) if isinstance(tr.attrs, dict) else {}
    if metrics.get("auto_choice") == "direct" and "auto_margin" in metrics:
        rec["transport_margin"] = float(metrics["auto_margin"])
    rec["grade"], rec["reasons"] = grade(rec, unconstrained=sol.info.get("envmap_constrained_by_data") is False)
    return rec


def dark_sky(lum: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """(N,) bool: the texels of ``sky`` (N,) bool whose luminance ``lum`` (N,) is at most VERDICT_DARK_LEVEL x the
    99th percentile of the sky's (held at the radiance >= 0 bound); a black sky (99th percentile 0) is dark
    everywhere."""
    if not sky.any():
        return np.zeros_like(sky)
    white = float(np.percentile(lum[sky], 99))
    return sky & (lum <= VERDICT_DARK_LEVEL * white) if white > 0 else sky.copy()


def dark_sky_area(lum: np.ndarray, omega: np.ndarray, sky: np.ndarray) -> float:
    """The share of the solid angle of the texels ``sky`` (N,) bool that :func:`dark_sky` finds black; ``omega``
    (N,) the texels' solid angles (sr). No sky texel: 0."""
    if not sky.any():
        return 0.0
    return float(omega[dark_sky(lum, sky)].sum() / omega[sky].sum())


def black_light(lum: np.ndarray, omega: np.ndarray, black: np.ndarray, sky: np.ndarray) -> float:
    """The share of the sky's light that the texels ``black`` (N,) bool would hold at the sky's level: each counted
    at the median luminance of the texels of ``sky`` (N,) bool that are not black (a lamp is not the sky's level;
    a row's own median is not either where the black fills most of it and what is left of the row is a lamp's
    rim), over the sky's light so counted. lum, omega (N,): luminance and solid angle (sr) per texel. A black
    region in a dark room's dim walls holds a few thousandths of the light, a quarter of a sunlit sky about a
    quarter of it; an all-black sky all of it."""
    black = black & sky
    if not black.any():
        return 0.0
    ok = sky & ~black
    if not ok.any():
        return 1.0
    level = np.where(black, float(np.median(lum[ok])), lum)
    total = float((level[sky] * omega[sky]).sum())
    return float((level[black] * omega[black]).sum() / total) if total > 0 else 1.0


def grade(m: dict, unconstrained: bool = False) -> tuple[str, list[str]]:
    """(grade, reasons) from the measures of :func:`assess` (missing measures are not judged)."""
    red, yellow = [], []
    if unconstrained:
        red.append("one illumination and every albedo unknown: the priors, not the photo, drew the envmap")
    chi2 = m.get("chi2")
    frac = m.get("residual_fraction")
    small = frac is not None and frac <= VERDICT_RESIDUAL_RED
    if chi2 is not None and chi2 > VERDICT_CHI2_RED and not small:
        red.append(f"the model leaves a residual {np.sqrt(chi2):.1f}x the noise: the photo holds light, geometry or "
                   "outliers it lacks (interreflections, mesh, saturation, fireflies; see residual.exr)")
    elif chi2 is not None and chi2 > VERDICT_CHI2_RED:
        yellow.append(f"residual {np.sqrt(chi2):.1f}x the noise but {frac:.1%} of the photo: a small misfit the "
                      "model lacks, e.g. the sharp shadows of a light smaller than a texel (see residual.exr)")
    elif chi2 is not None and chi2 > VERDICT_CHI2_YELLOW:
        yellow.append(f"residual {np.sqrt(chi2):.1f}x the noise: the photo holds light or geometry the model lacks")
    uv, ua, ue = m.get("uncertain_visible_area"), m.get("uncertain_area"), m.get("uncertain_visible_energy")
    # the light the map does show where the photo barely sees: then a map mostly undetermined has nothing to stand on
    poorly = m.get("brightest_seen", 1.0) < VERDICT_SEEN_YELLOW and m.get("brightest_elevation_deg", 90.0) >= 0
    if uv is not None and uv > VERDICT_UNCERTAIN_RED and (ue is None or ue > VERDICT_LIGHT_RED or poorly):
        red.append(f"{uv:.0%} of the sky is not determined by the photo at the brightness it is shown"
                   + (f" ({ue:.0%} of the light)" if ue is not None and ue > VERDICT_LIGHT_RED else
                      ", and its brightest light is where the photo barely sees" if poorly else ""))
    elif uv is not None and uv > VERDICT_UNCERTAIN_RED:
        yellow.append(f"{uv:.0%} of the sky is not determined by the photo at the brightness it is shown, but holds "
                      f"{ue:.1%} of the light (a dark room's dim walls, say)")
    elif ua is not None and ua > VERDICT_UNCERTAIN_YELLOW:
        yellow.append(f"{ua:.0%} of the sky weakly determined (uncertainty above the value)")
    dark, filled = m.get("dark_sky_area", 0.0), m.get("dark_sky_area_solved", 0.0)
    # the light the black would hold at the sky's level (the area itself where that was not measured)
    light = max(m.get("dark_sky_light", dark), m.get("dark_sky_light_solved", filled))
    black = (f"{dark:.0%} of the sky is black (held at radiance 0)" if dark >= filled else
             f"{filled:.0%} of the sky came out black (held at radiance 0) before its row means filled it")
    if max(dark, filled) > VERDICT_DARK_YELLOW and light > VERDICT_LIGHT_RED:
        red.append(f"{black}, at the sky's level {light:.0%} of the light: the fit there answers what the model "
                   "cannot express, e.g. the sharp shadows of a light smaller than a texel; see residual.exr")
    elif dark > VERDICT_DARK_AREA_RED:
        red.append(f"{dark:.0%} of the sky is black (held at radiance 0): the map shows the lights the photo sees, "
                   f"not the place around them (at the sky's level {light:.1%} of the light: too dim to see)")
    elif max(dark, filled) > VERDICT_DARK_YELLOW:
        yellow.append(f"{black}, at the sky's level {light:.1%} of the light: the model may miss a light smaller "
                      "than a texel")
    below, el = m.get("below_horizon_energy", 0.0), m.get("brightest_elevation_deg", 90.0)
    if el < 0:
        red.append(f"the brightest light is below the horizon ({el:.1f} deg), seen only past the support's edge")
    if below > VERDICT_BELOW_RED:
        red.append(f"{below:.0%} of the energy below the horizon")
    elif below > VERDICT_BELOW_YELLOW:
        yellow.append(f"{below:.0%} of the energy below the horizon")
    if poorly:
        yellow.append(f"the brightest light is in a poorly seen direction (elevation {el:.0f} deg)")
    res = m.get("resolution_deg")
    if res is not None and res > VERDICT_RESOLUTION_YELLOW:
        yellow.append(f"the photo resolves the sky to about {res:.0f} deg ({m.get('resolved_values', 0):.0f} "
                      "independent values above the horizon): finer detail, a texture or a lamp's sharpness, is "
                      "the prior's")
    if m.get("pixels_rejected", 0.0) > VERDICT_REJECTED_YELLOW:
        yellow.append(f"{m['pixels_rejected']:.1%} of the pixels dropped as outliers (fireflies, hot pixels, glints "
                      "or geometry the model lacks; see residual.exr)")
    if m.get("pixels_excluded", 0.0) > VERDICT_EXCLUDED_YELLOW:
        yellow.append(f"{m['pixels_excluded']:.0%} of the pixels unusable (saturated, invalid or hot)")
    if m.get("sky_profile_area", 0.0) > 0:
        within = " within the misfit the model already leaves" if m.get("sky_profile_by_misfit") else ""
        yellow.append(f"{m['sky_profile_area']:.0%} of the sky shown as one value per elevation row: the photo did "
                      f"not tell its azimuthal detail from none{within} (solve.sky_profile)")
    mg = m.get("transport_margin")
    if mg is not None and mg > VERDICT_MARGIN_YELLOW:
        yellow.append(f"interreflections left out by a close margin ({mg:.2f} of the threshold)")
    if not unconstrained and m.get("object_albedo_unknown", 0.0) > 0.5:
        yellow.append("the object's albedo is unknown: with it estimated per pixel the low sky (a few degrees above "
                      "the horizon) comes out too bright, several times the truth on the bench's photographed "
                      "captures (give [albedo] object in capture.toml: its value, or \"uniform\" for one colour)")
    if m.get("noise_source") == "unknown":
        yellow.append("noise unknown: give noise_sigma in capture.toml")
    if red:
        return "red", red + yellow
    return ("yellow", yellow) if yellow else ("green", [])
