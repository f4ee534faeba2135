"""Luminance and chroma with their own smoothness: the envmap's colour from a more strongly smoothed solve.

A known-albedo edge solve (objcam.solvers.edges) fits each colour channel to its own data. Where the envmap is
dark in one channel (a brown overhang in the blue channel, say) that channel's radiance sits at the noise level
of the shadows that see it, and the bound x >= 0 clips it to zero in patches. The tonemapped comparison (gamma
1/2.2, per channel) sees a zero next to a dim true value as a large error: on the bench's courtyard target 250 of
1,088 texels of the blue channel came out 0, and its blue SSIM was 0.64 against 0.85-0.86 for red and green.

Natural environment maps change colour more slowly than brightness (sky, foliage, walls: a few hues, with the
texture in the luminance), as image restoration has long used (denoising chroma more than luma). So the estimate
here takes its luminance and its chroma from two solves of the same problem that differ only in the smoothness
weight:

    X = l * R,   l = mean_c X_lum[:, c],   R[:, c] = X_chroma[:, c] / mean_c X_chroma[:, c],

``X_lum`` the edge solve at ``ls`` and ``X_chroma`` the edge solve at ``factor x ls`` (both exact minimisers of
their own objectives). The channel mean of X is exactly the luminance solve's, and X >= 0. Texels where the chroma
solve is black in every channel keep the luminance solve's own colour.

Measured on the bench (bench/results.md, core notes): with ls 1.5 sigma and factor 10, courtyard SSIM 0.785 ->
0.856, forest 0.775 -> 0.772. Taking the luminance from an edge solve of the channel-mean data alone was worse
(courtyard 0.687 against 0.810 at ls 0.5 sigma), as was fitting the luminance to all channels at the chroma
held fixed (forest 0.784 against 0.797): the per-channel solve's own channel mean is the better luminance.
"""

from __future__ import annotations

import numpy as np

#: A texel whose chroma-solve mean is below this fraction of the largest is "black" (its ratios are undefined).
BLACK = 1e-9


def chroma_ratios(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, C) ratios of each channel to the channel mean of X (N, C) >= 0, and (N,) bool: defined (not black)."""
    X = np.maximum(np.asarray(X, dtype=np.float64), 0.0)
    m = X.mean(axis=1)
    ok = m > BLACK * max(float(m.max(initial=0.0)), 1e-300)
    R = np.ones_like(X)
    R[ok] = X[ok] / m[ok, None]
    return R, ok


def luminance_with_chroma(X_lum: np.ndarray, X_chroma: np.ndarray) -> np.ndarray:
    """(N, C): the channel mean of ``X_lum`` times the chroma ratios of ``X_chroma`` (module docstring); where
    ``X_chroma`` is black, ``X_lum`` itself."""
    X_lum = np.maximum(np.asarray(X_lum, dtype=np.float64), 0.0)
    if X_lum.shape != np.shape(X_chroma):
        raise ValueError(f"shapes differ: {X_lum.shape} vs {np.shape(X_chroma)}")
    R, ok = chroma_ratios(X_chroma)
    out = X_lum.copy()
    out[ok] = X_lum[ok].mean(axis=1, keepdims=True) * R[ok]
    return out
