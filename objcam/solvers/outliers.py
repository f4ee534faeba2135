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


#: objcam.solvers.plan.params noise_model=brightness: pixels are binned by predicted brightness in steps of this
#: factor (a bin's pixels differ by less than ~40% in brightness, so a nearly uniform plane is one bin whatever its
#: small variations, and a bright object its own), and a bin of fewer than BRIGHTNESS_MIN_PIXELS (a robust variance
#: to ~10%) joins its neighbour towards the median pixel
BRIGHTNESS_STEP = np.sqrt(2.0)
BRIGHTNESS_MIN_PIXELS = 100


def brightness_bins(p: np.ndarray, step: float = BRIGHTNESS_STEP, min_pixels: int = BRIGHTNESS_MIN_PIXELS
                    ) -> list[np.ndarray]:
    """The pixels' indices grouped by brightness p (M,) >= 0, darkest group first: bins of log p of width log
    ``step`` centred on the median pixel; a bin of fewer than ``min_pixels`` joins its neighbour towards the
    median (pixels at p <= 0 count as the darkest bin)."""
    p = np.asarray(p, dtype=np.float64)
    if p.size == 0:
        return []
    pos = p > 0
    if not pos.any():
        return [np.arange(p.size)]
    k = np.empty(p.size, dtype=np.int64)
    k[pos] = np.floor(np.log(p[pos] / np.median(p[pos])) / np.log(step) + 0.5)
    k[~pos] = k[pos].min()
    ks, inv, counts = np.unique(k, return_inverse=True, return_counts=True)
    into = np.arange(ks.size)  # the bin each bin's pixels go to
    centre = int(np.searchsorted(ks, 0))  # the median pixel's bin
    # from both ends inwards: a bin too small for a robust spread hands its pixels to its neighbour
    for i in list(range(centre)) + list(range(ks.size - 1, centre, -1)):
        if counts[i] < min_pixels:
            nxt = i + 1 if i < centre else i - 1
            counts[nxt] += counts[i]
            into[into == i] = nxt
    return [np.flatnonzero(into[inv] == b) for b in np.unique(into)]


def isotonic_increasing(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(K,) the non-decreasing sequence nearest ``values`` (K,) in weighted least squares (``weights`` (K,) > 0), by
    pool adjacent violators. As scipy.optimize.isotonic_regression, whose import (~0.1 s: scipy.optimize and what it
    pulls in) the first solve of a process paid inside its timer, for the few brightness bins here."""
    v = np.asarray(values, dtype=np.float64).ravel()
    w = np.asarray(weights, dtype=np.float64).ravel()
    if v.shape != w.shape or np.any(w <= 0):
        raise ValueError(f"values {v.shape} and weights {w.shape} must match, weights > 0")
    means, sums, counts = [], [], []  # the pooled blocks: weighted mean, weight, length
    for x, wx in zip(v, w):
        m, s, n = float(x), float(wx), 1
        while means and means[-1] > m:  # a violator: pool with the block before
            s0 = sums.pop()
            m = (means.pop() * s0 + m * s) / (s0 + s)
            s += s0
            n += counts.pop()
        means.append(m)
        sums.append(s)
        counts.append(n)
    return np.repeat(means, counts)


def brightness_weights(y: np.ndarray, fit: np.ndarray, sigma_abs: float | None, ordinary: float = 3.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel weights for a noise that grows with brightness, from a fit's residuals: (weights (M,), the
    variance per brightness bin (B,), darkest first, in absolute units squared).

    The pixels are grouped by the fit's channel mean (:func:`brightness_bins`); each bin's variance is the square
    of its residuals' :func:`robust_scale` (all channels), floored at the stated noise's ``sigma_abs ** 2`` (None:
    no floor) so that no pixel counts for more than the noise allows, then made non-decreasing in brightness
    (isotonic regression weighted by the bins' sizes: shot noise and a model's relative errors grow with the
    signal; a dark bin's larger misfit, e.g. at shadow edges, is pooled with the brighter bins instead of taking
    the shadows' weight). A pixel's weight is ``min(1, ordinary^2 v_med / v)``, v_med the median pixel's variance:
    1 for pixels whose misfit is within ``ordinary`` times a typical pixel's (ordinary misfit, as the outlier rule
    counts it: objcam.solvers.plan.defaults.OUTLIER_CLEAN_SPREAD; the data term's weight against a prior is
    unchanged), the inverse of the excess beyond (a bright object's shading the model lacks, a path tracer's noise
    on bright pixels). y, fit: (M, C)."""
    y = np.asarray(y, dtype=np.float64)
    fit = np.asarray(fit, dtype=np.float64)
    if y.shape != fit.shape or y.ndim != 2:
        raise ValueError(f"y and fit must be (M, C) of one shape, got {y.shape} and {fit.shape}")
    if y.shape[0] == 0:
        return np.zeros(0), np.zeros(0)
    r = y - fit
    parts = brightness_bins(np.abs(fit).mean(axis=1))
    floor = max(float(sigma_abs or 0.0) ** 2, 1e-300)
    raw = np.array([max(robust_scale(r[part]) ** 2, floor) for part in parts])
    # (pool adjacent violators: the weighted least-squares non-decreasing fit)
    per_bin = isotonic_increasing(raw, np.array([len(p) for p in parts], dtype=np.float64))
    v = np.empty(len(y))
    for b, part in enumerate(parts):
        v[part] = per_bin[b]
    return np.minimum(1.0, ordinary ** 2 * float(np.median(v)) / v), per_bin
