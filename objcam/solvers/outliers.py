"""Outlier pixels: fitted pixels whose residual no reading of the noise explains.

Least squares lets a handful of pixels far off the model pull the whole envmap: a path tracer's fireflies, a hot
pixel, a specular glint on a "diffuse" object, a misregistered silhouette edge. On the hard-case suite (issue 22,
bench/results.md) 1-7% of a target's pixels sat beyond 6x the noise and carried up to 97% of its chi-squared; the
envmap solved without them scored SSIM 0.674 -> 0.779 (median, 0.5% noise) and 0.706 -> 0.774 (2%).

The rule, after a first fit: a pixel is an outlier when any channel's residual exceeds ``k`` times the larger of
the stated noise (``noise_sigma`` per fitted pixel, absolute) and the residuals' own robust scale (1.4826 x their
median absolute deviation: the model's misfit where it exceeds the noise, so a broadly imperfect model does not
lose its ordinary pixels). Beyond ``max_share`` of the pixels nothing is removed: the model, not a few pixels,
is wrong there, and the verdict's chi-squared says so.
"""

from __future__ import annotations

import numpy as np

#: MAD of a normal distribution over its standard deviation's reciprocal: 1.4826 x MAD estimates sigma.
MAD_TO_SIGMA = 1.4826


def robust_scale(r: np.ndarray) -> float:
    """1.4826 x the median absolute deviation of ``r`` (any shape): its standard deviation for normal values,
    unmoved by a few wild ones."""
    r = np.asarray(r, dtype=np.float64).ravel()
    if r.size == 0:
        return 0.0
    return float(MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))


def outlier_rows(y: np.ndarray, fit: np.ndarray, sigma_abs: float | None, k: float,
                 max_share: float) -> tuple[np.ndarray, dict]:
    """(rows (M,) bool, record) of the fitted pixels y (M, C) the fit (M, C) misses by more than k x
    max(sigma_abs, robust scale of the residuals), any channel; none when more than ``max_share`` of them would go.

    sigma_abs: the stated noise of one fitted pixel value (absolute units; None or 0 when unknown). The record
    holds the counts and scales for solve.json."""
    if k <= 0 or max_share <= 0:
        raise ValueError("k and max_share must be positive")
    y = np.asarray(y, dtype=np.float64)
    r = y - np.asarray(fit, dtype=np.float64)
    spread = robust_scale(r)
    scale = max(spread, float(sigma_abs or 0.0))
    rec = {"threshold": k, "robust_scale": spread, "noise": float(sigma_abs or 0.0), "pixels": 0, "share": 0.0}
    if scale <= 0 or r.size == 0:
        return np.zeros(len(y), bool), rec
    amax = np.abs(r).max(axis=1)
    rows = amax > k * scale
    rec["weights"] = np.where(rows, k * scale / np.maximum(amax, 1e-300), 1.0)  # Huber's: k scale / |r| beyond
    share = float(rows.mean())
    sq = r * r
    rec.update(pixels=int(rows.sum()), share=share,
               chi2_share=float(sq[rows].sum() / max(float(sq.sum()), 1e-300)))
    if share > max_share:
        rec["kept"] = f"more than {max_share:.0%} of the pixels: the model, not a few pixels, misfits"
        return np.zeros(len(y), bool), rec
    return rows, rec
