"""Envmap and image error metrics (used by the ``evaluate`` stage and the benchmark).

All envmaps are (H, 2H, 3) linear RGB on one :class:`~objcam.envmap.EnvGrid`; ``mask`` (H, 2H) bool marks the
texels the solve kept (the only ones compared).

- Relative RMSE (headline, as in the method's paper): plain per texel, ``sqrt(mean (est - truth)^2) /
  mean(truth)`` over kept texels and all channels. ``relative_rmse_solid_angle`` weights each texel by its solid
  angle instead (an error per steradian rather than per texel).
- Tonemapped comparisons: both maps are divided by the truth's 99th percentile (over the channel values of the kept
  texels; its maximum where that percentile is a plateau, half the values within 5% of it: a dark room's uniform walls,
  which it would show as one flat white), clipped to [0, 1] and raised to 1/2.2; texels outside the mask are set to
  0 in both. Then RMSE over kept texels and SSIM (Wang et al. 2004: Gaussian window sigma 1.5 truncated at radius 5
  -- 11 x 11 -- or at radius H on grids with fewer than 5 rows, C1 = (0.01)^2, C2 = (0.03)^2 for data range 1,
  computed per channel and averaged). The SSIM map is computed on the whole grid with spherical padding (columns
  wrap in azimuth; rows continue across a pole into the row itself shifted by half a turn) and averaged over kept
  texels. ``ssim_masked`` (:func:`masked_ssim`) instead ignores the texels outside the mask (normalised
  convolution), so the border between solved and unsolved texels earns no credit; reported beside ``ssim``.
- Peak direction: the brightest kept texel of the luminance map (Rec. 709 weights), refined to the mean
  direction of the 4-connected region (wrapping in azimuth) of kept texels at >= 50 % of the peak luminance
  containing it, each texel weighted by luminance x solid angle. ``brightest_angle_deg`` is the angle between the
  estimate's and the truth's peak directions.
- ``scale_invariant=True`` first multiplies the estimate by :func:`best_scale` (the least-squares scale over
  kept texels and channels) for methods that recover radiance only up to a global factor.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from objcam.envmap import EnvGrid

LUMA = np.array([0.2126, 0.7152, 0.0722])
SSIM_SIGMA = 1.5
SSIM_RADIUS = 5
PEAK_FRACTION = 0.5


def _check(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    est = np.asarray(est, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if est.shape != truth.shape:
        raise ValueError(f"estimate {est.shape} and truth {truth.shape} differ in shape")
    if est.ndim != 3 or est.shape[1] != 2 * est.shape[0]:
        raise ValueError(f"envmaps must be (H, 2H, C), got {est.shape}")
    m = np.ones(est.shape[:2], dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != est.shape[:2]:
        raise ValueError(f"mask {m.shape} does not match envmap {est.shape[:2]}")
    if not m.any():
        raise ValueError("mask keeps no texels")
    return est, truth, m


def luminance(env: np.ndarray) -> np.ndarray:
    """(H, W) Rec. 709 luminance of an (H, W, 3) map; a single-channel (H, W[, 1]) map is returned as is."""
    env = np.asarray(env, dtype=np.float64)
    if env.ndim == 2:
        return env
    if env.shape[-1] == 1:
        return env[..., 0]
    return env @ LUMA


def best_scale(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Least-squares s minimising ``sum (s est - truth)^2`` over kept texels and channels; 1.0 if est is 0 there."""
    est, truth, m = _check(est, truth, mask)
    e, t = est[m], truth[m]
    ee = float(np.sum(e * e))
    return float(np.sum(e * t) / ee) if ee > 0 else 1.0


def best_scale_channels(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(C,) least-squares scale per channel over kept texels (or pixels): the ambiguity of a joint albedo/envmap
    solve is one scale per colour channel; 1.0 for a channel whose estimate is 0 there.

    est, truth: (H, W, C); mask: (H, W) bool (None: all)."""
    est = np.asarray(est, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    m = np.ones(est.shape[:2], dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    e, t = est[m], truth[m]
    ee = np.sum(e * e, axis=0)
    return np.where(ee > 0, np.sum(e * t, axis=0) / np.where(ee > 0, ee, 1.0), 1.0)


def relative_rmse(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
                  solid_angle: bool = False) -> float:
    """RMSE / mean(truth) over kept texels and channels; per texel, or per steradian with ``solid_angle``."""
    est, truth, m = _check(est, truth, mask)
    w = EnvGrid(est.shape[0]).solid_angles()[m] if solid_angle else np.ones(int(m.sum()))
    w = w[:, None]
    d2 = (est[m] - truth[m]) ** 2
    mse = np.sum(w * d2) / (np.sum(w) * est.shape[2])
    mean = np.sum(w * truth[m]) / (np.sum(w) * est.shape[2])
    return float(np.sqrt(mse) / mean) if mean > 0 else float("inf")


#: the share of the kept channel values within PLATEAU_TOLERANCE of the tonemap's percentile from which that
#: percentile is a plateau: a flat background filling most of the sky (a dark room's uniform walls with a few
#: lamps; noisy, as a chrome ball's would be, just under the percentile), which the percentile would map to white,
#: leaving that much of the tonemapped truth within 2% of one value (0.95^(1 / 2.2) = 0.977) that every map at
#: least as bright matches (room2: SSIM 1 for the constant map, a metric that cannot fail). There the tonemap's
#: white is the maximum. On the hard suite's truths room2 holds all its sky's values there (half the sphere's: its
#: floor is the other half); the others at most 29% (sun8's sky low around the sun), the core HDRIs 1-2%.
PLATEAU_SHARE = 0.5
PLATEAU_TOLERANCE = 0.05


def tonemap_scale(truth: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.0) -> float:
    """The truth's ``percentile`` over the channel values of the kept texels; its maximum instead where at least
    :data:`PLATEAU_SHARE` of those values lie within :data:`PLATEAU_TOLERANCE` of the percentile (a flat
    background: see there) or the percentile is not positive; 1 for a black truth."""
    truth = np.asarray(truth, dtype=np.float64)
    m = np.ones(truth.shape[:2], dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    vals = truth[m]
    if not vals.size:
        return 1.0
    s = float(np.percentile(vals, percentile))
    if s <= 0 or np.mean(vals >= (1.0 - PLATEAU_TOLERANCE) * s) >= PLATEAU_SHARE:
        s = float(vals.max())
    return s if s > 0 else 1.0


#: the display gamma of :func:`tonemap` (and so of the tonemapped metrics)
TONEMAP_GAMMA = 2.2


def tonemap(env: np.ndarray, scale: float, gamma: float = TONEMAP_GAMMA) -> np.ndarray:
    """``clip(env / scale, 0, 1) ** (1 / gamma)``."""
    return np.clip(np.asarray(env, dtype=np.float64) / scale, 0.0, 1.0) ** (1.0 / gamma)


def _gaussian_taps(sigma: float, radius: int) -> np.ndarray:
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (k / sigma) ** 2)
    return w / w.sum()


def pad_sphere(img: np.ndarray, r: int) -> np.ndarray:
    """Pad a lat-long image (H, W, ...) by ``r`` texels on every side, spherically.

    Columns wrap in azimuth; the row above row 0 is row 0 half a turn away (the pole's other side), the one above
    that row 1 half a turn away, and likewise at the bottom. Requires ``r <= H``.
    """
    h, w = img.shape[:2]
    if r == 0:
        return img
    if r > h:
        raise ValueError(f"pad {r} exceeds height {h}")
    top = np.roll(img[:r][::-1], w // 2, axis=1)
    bot = np.roll(img[h - r :][::-1], w // 2, axis=1)
    v = np.concatenate([top, img, bot], axis=0)
    return np.concatenate([v[:, w - r :], v, v[:, :r]], axis=1)  # r <= H < W


def _blur(img: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Separable Gaussian on a spherically padded (H, W, C) image; returns (H, W, C)."""
    r = (taps.size - 1) // 2
    p = pad_sphere(img, r)
    h, w = img.shape[:2]
    rows = sum(t * p[k : k + h] for k, t in enumerate(taps))
    return sum(t * rows[:, k : k + w] for k, t in enumerate(taps))


def _ssim_from_moments(a: np.ndarray, b: np.ndarray, mean, data_range: float) -> np.ndarray:
    """Per-pixel SSIM (H, W), averaged over channels, of (H, W, C) images whose local means ``mean(x)`` gives
    (the window, padding and mask are the caller's): Wang et al. 2004, C1 = (0.01 L)^2, C2 = (0.03 L)^2."""
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    mu_a, mu_b = mean(a), mean(b)
    saa = mean(a * a) - mu_a**2
    sbb = mean(b * b) - mu_b**2
    sab = mean(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * sab + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2)
    return (num / den).mean(axis=-1)


def ssim_map(a: np.ndarray, b: np.ndarray, data_range: float = 1.0, sigma: float = SSIM_SIGMA,
             radius: int = SSIM_RADIUS) -> np.ndarray:
    """Per-texel SSIM (H, W) of two lat-long images (H, W[, C]), averaged over channels.

    Wang et al. 2004 with a Gaussian window (``sigma``, truncated at ``min(radius, H)`` and renormalised),
    spherical padding (:func:`pad_sphere`), C1 = (0.01 L)^2, C2 = (0.03 L)^2, L = ``data_range``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    taps = _gaussian_taps(sigma, min(radius, a.shape[0]))
    return _ssim_from_moments(a, b, lambda x: _blur(x, taps), data_range)


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, data_range: float = 1.0) -> float:
    """Mean of :func:`ssim_map` over ``mask`` (all texels if None)."""
    s = ssim_map(a, b, data_range)
    return float(s.mean() if mask is None else s[np.asarray(mask, dtype=bool)].mean())


def masked_ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray, data_range: float = 1.0,
                sigma: float = SSIM_SIGMA, radius: int = SSIM_RADIUS) -> float:
    """SSIM that ignores texels outside ``mask`` instead of zeroing them: mean over kept texels of the SSIM whose
    local means, variances and covariance are normalised convolutions (Gaussian window restricted to kept texels,
    renormalised), so the edge between kept texels and the unsolved region gives no free structure.

    a, b: (H, 2H[, C]) lat-long maps (tonemapped); mask: (H, 2H) bool. Equal to :func:`ssim` when every texel is
    kept. Same window, padding and constants as :func:`ssim_map`.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    m = np.asarray(mask, dtype=bool)
    w = m[..., None].astype(np.float64)
    taps = _gaussian_taps(sigma, min(radius, a.shape[0]))
    wsum = np.maximum(_blur(w, taps), 1e-12)

    def mean(x: np.ndarray) -> np.ndarray:
        return _blur(w * x, taps) / wsum

    return float(_ssim_from_moments(a, b, mean, data_range)[m].mean())


def _wrapped_component(region: np.ndarray, seed: tuple[int, int]) -> np.ndarray:
    """The 4-connected component of ``region`` (H, W) containing ``seed``, with columns wrapping."""
    labels, n = ndimage.label(region)
    parent = list(range(n + 1))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for r in np.flatnonzero(region[:, 0] & region[:, -1]):
        a, b = find(int(labels[r, 0])), find(int(labels[r, -1]))
        if a != b:
            parent[a] = b
    root = find(int(labels[seed]))
    same = np.array([find(i) == root for i in range(n + 1)])
    same[0] = False
    return same[labels]


def brightest_region(env: np.ndarray, mask: np.ndarray | None = None, fraction: float = PEAK_FRACTION
                     ) -> np.ndarray | None:
    """(H, W) bool: the brightest source of a lat-long map (H, 2H[, 3]): the connected region (4-neighbours,
    wrapping in azimuth) of kept texels with luminance >= ``fraction`` x the brightest kept texel's that contains
    it. None if no kept texel is brighter than 0."""
    lum = luminance(env)
    m = np.ones(lum.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    lm = np.where(m, lum, -np.inf)
    flat = int(np.argmax(lm))
    peak = lm.flat[flat]
    if not np.isfinite(peak) or peak <= 0:
        return None
    return _wrapped_component(m & (lum >= fraction * peak), np.unravel_index(flat, lm.shape))


def region_centre(env: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Unit world direction (3,): the luminance x solid-angle weighted mean direction of the texels ``region``
    (H, W) bool of a lat-long map (H, 2H[, 3]); the region's brightest texel's direction where the weights cancel."""
    grid = EnvGrid(region.shape[0])
    lum = luminance(env)
    wts = (lum * grid.solid_angles())[region]
    d = (grid.directions()[region] * wts[:, None]).sum(axis=0)
    nrm = np.linalg.norm(d)
    if nrm > 0:
        return d / nrm
    return grid.directions()[np.unravel_index(int(np.argmax(np.where(region, lum, -np.inf))), lum.shape)]


def brightest_direction(env: np.ndarray, mask: np.ndarray | None = None, fraction: float = PEAK_FRACTION) -> np.ndarray:
    """Unit world direction (3,) of the brightest source of a lat-long map (H, 2H[, 3]): the
    :func:`region_centre` of its :func:`brightest_region`. NaNs if no kept texel is brighter than 0."""
    region = brightest_region(env, mask, fraction)
    return np.full(3, np.nan) if region is None else region_centre(env, region)


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle in degrees between two unit vectors (NaN if either is NaN)."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
        return float("nan")
    # atan2 of |u x v| and u . v: accurate for tiny angles, unlike arccos.
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v)), np.dot(u, v))))


def brightest_angle_deg(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Angle in degrees between the :func:`brightest_direction` of the estimate and of the truth."""
    return angle_deg(brightest_direction(est, mask), brightest_direction(truth, mask))


def envmap_metrics(est: np.ndarray, truth: np.ndarray, kept_mask: np.ndarray | None = None,
                   scale_invariant: bool | str = False) -> dict[str, float]:
    """All envmap metrics as plain floats.

    est, truth: (H, 2H, 3) linear radiance on the same grid; kept_mask: (H, 2H) bool (None: all texels).
    scale_invariant: False, True (one global :func:`best_scale`) or "channel" (:func:`best_scale_channels`, the
    ambiguity of a joint albedo/envmap solve).
    Keys: ``relative_rmse`` (plain per texel, the headline), ``relative_rmse_solid_angle``, ``tonemapped_rmse``,
    ``ssim`` (tonemapped, mean over kept texels), ``ssim_masked`` (:func:`masked_ssim`), ``brightest_angle_deg``,
    ``scale`` (the factor applied to est: :func:`best_scale` when ``scale_invariant``, else 1.0; with "channel"
    the mean of the per-channel factors, listed in ``scale_channels``) and ``best_scale`` (always reported).
    """
    est, truth, m = _check(est, truth, kept_mask)
    s_best = best_scale(est, truth, m)
    extra: dict = {}
    if scale_invariant == "channel":
        sc = best_scale_channels(est, truth, m)
        e = est * sc
        s = float(np.mean(sc))
        extra["scale_channels"] = [float(v) for v in sc]
    else:
        s = s_best if scale_invariant else 1.0
        e = est * s
    tm_s = tonemap_scale(truth, m)
    te = np.where(m[..., None], tonemap(e, tm_s), 0.0)
    tt = np.where(m[..., None], tonemap(truth, tm_s), 0.0)
    return {
        "relative_rmse": relative_rmse(e, truth, m),
        "relative_rmse_solid_angle": relative_rmse(e, truth, m, solid_angle=True),
        "tonemapped_rmse": float(np.sqrt(np.mean((te[m] - tt[m]) ** 2))),
        "ssim": ssim(te, tt, m),
        "ssim_masked": masked_ssim(te, tt, m),
        "brightest_angle_deg": brightest_angle_deg(e, truth, m),
        "scale": float(s),
        "best_scale": float(s_best),
        **extra,
    }


def image_ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, data_range: float = 1.0) -> float:
    """SSIM of two ordinary (planar) images (H, W[, C]), mean over ``mask``: Wang et al. 2004 with the Gaussian
    window of :func:`ssim_map` (sigma 1.5, radius 5) and mirror padding at the borders, averaged over channels."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]

    def blur(x):
        return ndimage.gaussian_filter(x, sigma=(SSIM_SIGMA, SSIM_SIGMA, 0), mode="mirror",
                                       truncate=SSIM_RADIUS / SSIM_SIGMA)

    s = _ssim_from_moments(a, b, blur, data_range)
    return float(s.mean() if mask is None else s[np.asarray(mask, dtype=bool)].mean())


def albedo_metrics(est: np.ndarray, truth: np.ndarray, mask: np.ndarray, pinned: bool = False) -> dict:
    """Errors of an estimated albedo image, as estimated and after the best-fit scale per channel.

    est, truth: (H, W, 3) albedo in [0, 1] on the (pooled) image; mask: (H, W) bool, the pixels whose albedo was
    estimated. ``pinned``: the solve fixed the scale (pixels of known albedo, ``scale_ambiguous`` false), so the
    headline figures compare the albedo as estimated; otherwise (the joint solve's per-channel ambiguity) after
    the best-fit scale per channel. Headline: ``albedo_relative_rmse`` (RMSE / mean(truth) over the masked
    pixels and channels), ``albedo_ssim`` (:func:`image_ssim`, data range 1, both images 0 outside the mask, mean
    over the mask), ``albedo_scale`` (the per-channel factors applied to est before them: 1 when pinned),
    ``albedo_scored_as`` ("as estimated" / "fitted scale"), ``albedo_pixels``. Always beside them, named as such:
    ``albedo_fitted_scale`` (the best-fit factors), ``albedo_relative_rmse_fitted_scale`` and
    ``albedo_ssim_fitted_scale`` (the figures after it), ``albedo_relative_rmse_unscaled`` and
    ``albedo_ssim_unscaled``, and ``albedo_mean_ratio`` (per channel: mean estimate / mean truth, no scale).
    """
    est = np.asarray(est, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if est.shape != truth.shape or m.shape != est.shape[:2]:
        raise ValueError(f"albedo {est.shape}, truth {truth.shape} and mask {m.shape} do not match")
    if not m.any():
        raise ValueError("no pixel with an estimated albedo")
    t = np.where(m[..., None], truth, 0.0)
    mean = float(t[m].mean())

    def scored(sc: np.ndarray) -> tuple[float, float]:
        e = np.where(m[..., None], est * sc, 0.0)
        d = e[m] - t[m]
        rmse = float(np.sqrt(np.mean(d * d)) / mean) if mean > 0 else float("inf")
        return rmse, image_ssim(np.clip(e, 0, 1), np.clip(t, 0, 1), m)

    fitted = best_scale_channels(est, truth, m)
    rm_f, ss_f = scored(fitted)
    rm_u, ss_u = scored(np.ones(3))
    tm = t[m].mean(axis=0)
    return {
        "albedo_relative_rmse": rm_u if pinned else rm_f,
        "albedo_ssim": ss_u if pinned else ss_f,
        "albedo_scale": [1.0, 1.0, 1.0] if pinned else [float(v) for v in fitted],
        "albedo_scored_as": "as estimated" if pinned else "fitted scale",
        "albedo_relative_rmse_fitted_scale": rm_f,
        "albedo_ssim_fitted_scale": ss_f,
        "albedo_fitted_scale": [float(v) for v in fitted],
        "albedo_relative_rmse_unscaled": rm_u,
        "albedo_ssim_unscaled": ss_u,
        "albedo_mean_ratio": [float(a / b) if b > 0 else None for a, b in zip(est[m].mean(axis=0), tm)],
        "albedo_pixels": int(m.sum()),
    }


def image_relative_rmse(pred: np.ndarray, target: np.ndarray, valid: np.ndarray | None = None) -> float:
    """RMSE / mean(target) over valid pixels (and all channels).

    pred, target: same shape, (H, W[, C]) images or (M[, C]) pixel lists; valid: bool of the leading shape
    (H, W) or (M,) (None: all).
    """
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.shape != target.shape:
        raise ValueError(f"prediction {pred.shape} and target {target.shape} differ in shape")
    if valid is None:
        p, t = pred.ravel(), target.ravel()
    else:
        v = np.asarray(valid, dtype=bool)
        if v.shape != pred.shape[: v.ndim]:
            raise ValueError(f"valid mask {v.shape} does not match {pred.shape}")
        p, t = pred[v].ravel(), target[v].ravel()
    if p.size == 0:
        raise ValueError("no valid pixels")
    mean = float(t.mean())
    rmse = float(np.sqrt(np.mean((p - t) ** 2)))
    return rmse / mean if mean > 0 else float("inf")
