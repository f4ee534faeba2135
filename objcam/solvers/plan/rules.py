"""The rules of the solve's plan: which weights and which envmap basis each solve gets.

* :func:`texel_group` and :func:`basis_info`: the merged envmap basis (objcam.solvers.basis) per kind of solve;
* :func:`noise_ls`: the smoothness weight ls from a target's noise when it is not given;
* :func:`discrepancy_sigma`: the absolute pixel noise the discrepancy rule (auto_reg) needs.

How each default was measured: :mod:`objcam.solvers.plan.defaults`.
"""

from __future__ import annotations

import numpy as np

from objcam.errors import StageError
from objcam.solvers.basis import unknowns
from objcam.solvers.plan.defaults import (
    EDGE_LS_PER_SIGMA,
    EDGE_LS_PER_SIGMA_SUPERSAMPLED,
    KNOWN_LS_REL,
    LR_SIGMA_REF,
    LS_HEIGHT,
    LS_NOISE_FACTOR,
    LS_RANGE,
    NOISE_FIT_SPREADS,
    TEXEL_GROUP_JOINT,
    TEXEL_GROUP_KNOWN,
)
from objcam.solvers.plan.params import SolveParams


def texel_group(params: SolveParams, known: bool) -> float:
    """The envmap basis' group size (objcam.solvers.basis) for this solve: 0 (texels) for method=adam."""
    if params.method == "adam":
        return 0.0
    if params.texel_group is not None:
        return float(params.texel_group)
    return TEXEL_GROUP_KNOWN if known else TEXEL_GROUP_JOINT


def basis_info(texel_index: np.ndarray, P, params: SolveParams, known: bool) -> dict:
    """solve.json's record of the envmap basis P over ``texel_index`` (objcam.solvers.basis; for a supersampled A
    the output-texel basis before refinement: the edge solve's refined count is in ``supersample``)."""
    return {"texel_group": texel_group(params, known), "unknowns": unknowns(texel_index, P)}



def noise_ls(target, pooled: np.ndarray, pooled_ok: np.ndarray, params: SolveParams, f: int = 1,
             linear: bool = False, supersample: int = 1, height: int = LS_HEIGHT) -> tuple[float, str]:
    """ls from the noise of one fitted pixel (the target's relative noise_sigma, given per photo pixel, over the
    f x f pooling; else estimated from the pooled image): ls_noise_factor x sigma^2, or x sigma when ``linear``
    (the known-albedo edge prior), within LS_RANGE (the noise sets how much the data can be trusted against the
    prior; measured on 128 x 128 targets, and transport's automatic pooling keeps larger photos at 8-32k fitted
    pixels); times :func:`height_factor` for an envmap of ``height`` rows (the output grid's)."""
    ls, _, source = noise_weights(target, pooled, pooled_ok, params, f, linear, supersample, height)
    return ls, source


def noise_weights(target, pooled: np.ndarray, pooled_ok: np.ndarray, params: SolveParams, f: int = 1,
                  linear: bool = False, supersample: int = 1, height: int = LS_HEIGHT) -> tuple[float, float, str]:
    """(ls, lr, the source of ls) from the noise of one fitted pixel, estimated once: ls as :func:`noise_ls`,
    lr as :func:`noise_lr`."""
    sigma, source = fitted_noise(target, pooled, pooled_ok, f)
    ls, source = _noise_ls(sigma, source, params, linear, supersample)
    if height != LS_HEIGHT:
        ls, source = ls * height_factor(height), f"{source}, x {height_factor(height):g} for {height} rows"
    return ls, noise_lr(sigma), source


def noise_lr(sigma: float | None) -> float:
    """The known-albedo edge prior's relative ridge weight for a relative noise ``sigma`` per fitted pixel:
    DEFAULT_LR_REL x min(1, sigma / LR_SIGMA_REF), so that the ridge keeps its ratio to ls = 1.5 sigma on quieter
    photos instead of outweighing the data (objcam.solvers.plan.defaults.LR_SIGMA_REF); DEFAULT_LR_REL when the
    noise is unknown (None or 0)."""
    from objcam.solvers.regularization import DEFAULT_LR_REL

    return DEFAULT_LR_REL * min(1.0, sigma / LR_SIGMA_REF) if sigma else DEFAULT_LR_REL


def height_factor(height: int) -> float:
    """(height / LS_HEIGHT)^4: the same prior at another envmap height (objcam.solvers.plan.defaults.LS_HEIGHT)."""
    return (float(height) / LS_HEIGHT) ** 4


def _noise_ls(sigma: float | None, source: str, params: SolveParams, linear: bool,
              supersample: int) -> tuple[float, str]:
    source = {"estimated": "estimated noise"}.get(source, source)
    if not sigma:
        return KNOWN_LS_REL, "default (noise unknown)"
    factor = params.ls_noise_factor
    if factor is None and linear:
        factor = EDGE_LS_PER_SIGMA if supersample == 1 else EDGE_LS_PER_SIGMA_SUPERSAMPLED
    elif factor is None:
        # a supersampled A (objcam.solvers.refine): mean diag(A^T A) shrinks ~s^4 and an output edge is s fine
        # edges, so s^3 keeps the output grid's weight (derived, not tuned: the bench measures the edge prior)
        factor = LS_NOISE_FACTOR * supersample**3
    ls = float(np.clip(factor * (sigma if linear else sigma**2), *LS_RANGE))
    return ls, f"{source} {sigma:.4f} per fitted pixel"


def noise_scale(chi2: float, values: int, unknowns: int) -> tuple[float, float]:
    """(factor on the stated noise, expected chi2) from a fit's chi-squared per value ``chi2`` at the stated noise,
    over ``values`` fitted pixel values with ``unknowns`` unknowns per value's channel: 1 unless chi2 lies below the
    expectation ``1 - unknowns / (values / 3)`` (a least-squares fit absorbs at most one value per unknown and
    channel) by more than NOISE_FIT_SPREADS x sqrt(2 / values); then sqrt(chi2 / expected), the noise the residual
    supports. Never above 1: a residual above the noise is model error, not noise (solve.noise_fit)."""
    if values <= 0 or not np.isfinite(chi2):
        return 1.0, float("nan")
    expected = max(1.0 - 3.0 * unknowns / values, 0.5)
    if chi2 >= expected - NOISE_FIT_SPREADS * np.sqrt(2.0 / values):
        return 1.0, expected
    return float(np.sqrt(max(chi2, 1e-6) / expected)), expected


def fitted_noise(target, pooled: np.ndarray, pooled_ok: np.ndarray, f: int,
                 estimator=None) -> tuple[float | None, str]:
    """(relative noise per fitted pixel, its source): the target's noise_sigma (per photo pixel) over the f x f
    pooling (the mean of f^2 independent pixels), else estimated from the pooled photo by ``estimator`` (image,
    valid) -> relative noise or None (default objcam.transport.auto.estimate_relative_noise, the mean-|Laplacian|
    reading that weights the prior; the verdict's chi2 takes estimate_pixel_noise, the photo's own noise);
    (None, "unknown") when neither is possible."""
    from objcam.transport.auto import estimate_relative_noise

    if target.noise_sigma:
        return float(target.noise_sigma) / max(int(f), 1), "noise_sigma"
    est = (estimator or estimate_relative_noise)(pooled, pooled_ok)
    return (float(est), "estimated") if est else (None, "unknown")


def discrepancy_sigma(target, y: np.ndarray, rule: str) -> float | None:
    """Absolute noise standard deviation of one pixel value for the discrepancy rule: the target's relative
    ``noise_sigma`` (capture.toml) times its median positive pixel value."""
    if rule != "discrepancy":
        return None
    if not target.noise_sigma:
        raise StageError(f"auto_reg=discrepancy needs the noise level of target {target.name!r}",
                         fix="give noise_sigma for the target in capture.toml, or use solve.auto_reg=gcv")
    from objcam.transport.auto import absolute_noise

    return float(absolute_noise(y, target.noise_sigma))


def relative_column_norms(gram_diag: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N,) each texel's column norm sqrt(diag(G)) over the median one above the horizon (over all texels when
    none is above): how strongly the photo sees each direction. gram_diag: (N,) diag(A^T A) (a channel mean);
    directions: (N, 3) the texels' unit directions, z up."""
    col = np.sqrt(np.clip(gram_diag, 0, None))
    up = directions[:, 2] > 0
    ref = float(np.median(col[up])) if up.any() else float(np.median(col))
    return col / max(ref, 1e-300)


def weak_texels(tr, fraction: float) -> np.ndarray:
    """(N,) bool: A's texels whose relative column norm (:func:`relative_column_norms` of the channel-mean
    A^T A) is under ``fraction``: directions the photo barely sees (a sliver below the horizon past the support's
    edge sees ~1e-4-0.05 of a typical texel on the hard suite; the lowest row above it 0.14-1.2). A texel above
    the horizon holding a source the transport placed there by the photo (objcam.transport.points: its column is
    the point's light, as dim as the source is low) is seen by construction and never weak (a lamp 1.8 deg up
    came to 0.088 and was dropped)."""
    grams = tr.gram()  # (C, N, N): only the diagonals are needed
    weak = relative_column_norms(np.einsum("cii->i", grams) / grams.shape[0], tr.directions) < fraction
    placed = placed_texels(tr)
    if placed.size:
        weak &= ~np.isin(np.asarray(tr.texel_index), placed)
    return weak


def placed_texels(tr) -> np.ndarray:
    """Full-grid indices of the texels above the horizon whose column is a point source the transport placed
    there by the photo (objcam.transport.points; ``tr.attrs["point_sources"]``), (k,) int64; none: empty."""
    placed = [s["texel"] for s in (getattr(tr, "attrs", None) or {}).get("point_sources") or []
              if s.get("elevation_deg", 0.0) > 0.0]
    return np.asarray(placed, np.int64)
