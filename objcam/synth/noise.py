"""The camera noise model of synthetic captures, in radiance units: Poisson shot noise for ``exposure`` electrons
per unit radiance plus Gaussian read noise, clipped at a white level (:func:`apply_noise`); the exposure that gives
the median pixel a chosen relative shot noise (:func:`auto_exposure`); a pixel's relative noise under the model
(:func:`relative_noise`); and a render's own Monte Carlo noise from two independent halves (:func:`mc_noise`).
"""

from __future__ import annotations

import math

import numpy as np


def auto_exposure(clean: np.ndarray, shot_noise: float) -> float:
    """Electrons per unit radiance giving the median positive pixel a relative shot noise of ``shot_noise``."""
    pos = clean[np.isfinite(clean) & (clean > 0)]
    med = float(np.median(pos)) if pos.size else 1.0
    return 1.0 / (shot_noise**2 * med)


def apply_noise(clean: np.ndarray, exposure: float, read_noise: float, white_level: float | None,
                rng: np.random.Generator, noise: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The camera model: Poisson(exposure * clean) electrons + N(0, read_noise^2) electrons, / exposure, clipped
    at ``white_level`` (radiance units). Returns (image float32, clipped mask (H, W) where any channel clipped).

    Mean = clean, variance = clean / exposure + (read_noise / exposure)^2 (below the white level).
    """
    img = np.asarray(clean, dtype=np.float64)
    if noise:
        electrons = rng.poisson(np.clip(img, 0.0, None) * exposure).astype(np.float64)
        electrons += rng.normal(0.0, read_noise, img.shape)
        img = electrons / exposure
    if white_level is not None:
        clipped = img >= white_level
        img = np.minimum(img, white_level)
    else:
        clipped = np.zeros(img.shape, dtype=bool)
    if clipped.ndim == 3:
        clipped = clipped.any(axis=2)
    return img.astype(np.float32), clipped


def mc_noise(a: np.ndarray, b: np.ndarray, mean: np.ndarray, w: float = 0.5) -> float:
    """Median relative Monte Carlo noise of ``mean = w a + (1 - w) b`` from two independent renders ``a``, ``b``
    (robust: 1.4826 x the median absolute deviation, over pixels with a positive mean)."""
    ok = mean > 1e-8 * max(float(mean.max()), 1e-30)
    if not ok.any():
        return 0.0
    # var(a - b) = var(a) + var(b); with var ~ 1/spp, var(mean) = var(a - b) * w (1 - w)
    dev = np.abs(a - b)[ok] * math.sqrt(w * (1 - w)) / mean[ok]
    return float(1.4826 * np.median(dev))


def relative_noise(level: float, exposure: float, read_noise: float) -> float:
    """Standard deviation over mean of a pixel of radiance ``level`` under the noise model."""
    e = level * exposure
    return math.sqrt(e + read_noise**2) / e if e > 0 else float("inf")
