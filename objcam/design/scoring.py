"""How good a camera one occluder makes: its per-texel uncertainty and per-pixel leverage maps and the few
numbers ``design.json`` reports, from its transport A and the shared absolute ridge weight.

Uncertainty ``sqrt(diag((A^T A + lr I)^-1))`` is radiance per unit pixel noise (the analysis stage's
definition, smoothness prior left out); a texel that lights no pixel is unresolved and gets the ridge bound
``1 / sqrt(lr)``. Summaries are over the upper hemisphere (texel centre above the plane's horizon): the lower
one lies below the plane and no occluder on it can see there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from objcam.envmap import EnvGrid
from objcam.threads import single_blas_thread
from objcam.transport.storage import Transport


@dataclass
class Scores:
    """Maps and numbers of one occluder.

    uncertainty: (H, W) on the envmap grid (the bound where an upper texel lights nothing, NaN below the
    horizon); leverage: (H', W') per pixel
    (NaN where the pixel sees no surface); view: (H', W') fraction of each pixel's samples landing on the
    occluder; numbers: the ``design.json`` entry (see :func:`score`).
    """

    uncertainty: np.ndarray
    leverage: np.ndarray
    view: np.ndarray
    singular_values: np.ndarray
    numbers: dict


def band_masks(grid: EnvGrid, zenith_deg: float, horizon_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(upper, zenith, horizon) (H, W) bool by texel-centre elevation: above 0, above ``zenith_deg``, and in
    (0, ``horizon_deg``)."""
    theta, _ = grid.centres()
    elev = 90.0 - np.degrees(theta)
    upper = elev > 0
    return upper, elev >= zenith_deg, upper & (elev < horizon_deg)


def azimuth_cv(rows: np.ndarray) -> float:
    """Mean over the envmap rows (R, W) of the coefficient of variation (std / mean) across azimuth: how much
    the uncertainty depends on the direction around the object, elevation set aside."""
    rows = np.asarray(rows, dtype=np.float64)
    return float(np.mean(rows.std(axis=1) / rows.mean(axis=1)))


def score(tr: Transport, lr: float, *, threshold: float, rank_tol: float, zenith_deg: float,
          horizon_deg: float) -> Scores:
    """Score one transport (C = 1) with the absolute ridge weight ``lr``.

    numbers: ``uncertainty_mean`` / ``uncertainty_worst`` (max) / ``uncertainty_median`` over the upper
    hemisphere, ``spread`` (worst / mean: 1 = perfectly uniform), ``azimuth_cv`` (:func:`azimuth_cv`: 0 =
    the same in every azimuth, as a symmetric occluder under a camera overhead would be), ``fraction_resolved`` (upper texels whose
    uncertainty is below ``threshold / sqrt(lr)``), ``uncertainty_zenith`` / ``uncertainty_horizon`` (means over
    the bands of :func:`band_masks`), ``effective_rank`` (singular values above ``rank_tol`` s_0),
    ``entropy_effective_rank``, ``ridge_dof``, ``leverage_sum`` / ``leverage_max``, ``pixels``, ``texels``.
    """
    from objcam import analysis as an
    from objcam.solvers import gram

    A = tr.A[0] if tr.channels == 1 else tr.A.mean(axis=0)
    grid = EnvGrid(tr.env_height)
    with single_blas_thread():
        G = gram(A)
    L = an.cholesky_factor(G, lr)
    h = an.leverage(A, lr, L=L)
    u = an.texel_uncertainty(None, lr, L=L)
    sv = an.singular_spectrum(A, G=G)
    bound = 1.0 / np.sqrt(lr)
    upper, zen, hor = band_masks(grid, zenith_deg, horizon_deg)
    u_map = an.to_grid(u, grid, tr.texel_index, fill=bound).astype(np.float64)
    u_map[~upper] = np.nan  # below the plane's horizon: no occluder on the plane sees there
    h_img = an.scatter_to_image(h, tr.pixel_index, tr.image_shape)
    view = an.scatter_to_image(tr.object_fraction, tr.pixel_index, tr.image_shape)
    uu = u_map[upper]
    numbers = {
        "uncertainty_mean": float(uu.mean()),
        "uncertainty_worst": float(uu.max()),
        "uncertainty_median": float(np.median(uu)),
        "spread": float(uu.max() / uu.mean()),
        "azimuth_cv": azimuth_cv(u_map[upper.any(axis=1)]),
        "fraction_resolved": float(np.mean(uu < threshold * bound)),
        "uncertainty_zenith": float(u_map[zen].mean()),
        "uncertainty_horizon": float(u_map[hor].mean()),
        "effective_rank": int(an.effective_rank(sv, rank_tol)),
        "entropy_effective_rank": float(an.entropy_effective_rank(sv)),
        "ridge_dof": float(an.ridge_dof(sv, lr)),
        "leverage_sum": float(h.sum()),
        "leverage_max": float(h.max()),
        "pixels": int(A.shape[0]),
        "texels": int(A.shape[1]),
        "occluder_pixels": int(np.count_nonzero(tr.object_fraction > 0)),
    }
    return Scores(u_map, h_img, view, sv, numbers)
