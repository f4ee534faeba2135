"""Trivial baselines beside every envmap score (issue 28): what a map that knows nothing about azimuth scores.

For a truth envmap and the solved-texel mask:

- the **constant map**: the truth's mean per channel over the kept texels, weighted by solid angle (the weighting
  of ``relative_rmse_solid_angle``), everywhere;
- the **row-mean map** (an oracle): the truth's mean per channel over each row's kept texels (texels of one row
  share one solid angle, so that mean is solid-angle weighted too). It knows every elevation's brightness and
  nothing about azimuth: an estimate recovers light from the shadows only where it beats this map.

Both are scored with :func:`objcam.metrics.envmap_metrics` on the same mask as the estimate, unscaled (they are
made from the truth, so they already carry its scale). The skill of an estimate over a baseline is its SSIM minus
the baseline's (> 0: better) and its tonemapped RMSE over the baseline's (< 1: better).
"""

from __future__ import annotations

import numpy as np

from objcam.envmap import EnvGrid
from objcam.metrics import envmap_metrics

BASELINES = ("constant", "row_mean")
# the metrics reported for each baseline (the estimate's own keys)
BASELINE_KEYS = ("ssim", "ssim_masked", "tonemapped_rmse", "relative_rmse", "relative_rmse_solid_angle",
                 "brightest_angle_deg")


def constant_map(truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, 2H, C) map equal everywhere to the truth's solid-angle weighted mean per channel over ``mask``.

    truth: (H, 2H, C) linear radiance; mask: (H, 2H) bool, at least one texel kept."""
    truth = np.asarray(truth, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    w = EnvGrid(truth.shape[0]).solid_angles()[m]
    mean = (truth[m] * w[:, None]).sum(axis=0) / w.sum()
    return np.broadcast_to(mean, truth.shape).copy()


def row_mean_map(truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, 2H, C) map whose every texel holds the truth's mean per channel over the kept texels of its row
    (0 in rows with none kept).

    truth: (H, 2H, C) linear radiance; mask: (H, 2H) bool."""
    truth = np.asarray(truth, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)[..., None]
    n = m.sum(axis=1)  # (H, 1)
    rows = np.where(n > 0, (truth * m).sum(axis=1) / np.maximum(n, 1), 0.0)  # (H, C)
    return np.repeat(rows[:, None, :], truth.shape[1], axis=1)


def baseline_metrics(truth: np.ndarray, mask: np.ndarray) -> dict[str, dict[str, float]]:
    """{"constant": metrics, "row_mean": metrics}: each baseline scored against ``truth`` over ``mask`` with the
    estimate's metrics (the keys of :data:`BASELINE_KEYS`).

    truth: (H, 2H, C) linear radiance; mask: (H, 2H) bool."""
    out = {}
    for name, make in (("constant", constant_map), ("row_mean", row_mean_map)):
        m = envmap_metrics(make(truth, mask), truth, mask)
        out[name] = {k: m[k] for k in BASELINE_KEYS}
    return out


def skill(estimate: dict, baselines: dict[str, dict]) -> dict[str, float]:
    """The estimate's skill over each baseline, from metric dicts (the estimate's, :func:`baseline_metrics`'):
    ``ssim_over_<b>`` = SSIM - the baseline's (0: no better), ``ssim_masked_over_<b>`` likewise for the masked
    SSIM, ``tonemapped_rmse_over_<b>`` = tonemapped RMSE / the baseline's (1: no better; inf where the baseline's is 0).
    """
    out = {}
    for b, bm in baselines.items():
        out[f"ssim_over_{b}"] = float(estimate["ssim"] - bm["ssim"])
        if "ssim_masked" in estimate:
            out[f"ssim_masked_over_{b}"] = float(estimate["ssim_masked"] - bm["ssim_masked"])
        den = bm["tonemapped_rmse"]
        # tonemapped values lie in [0, 1]: below 1e-12 the baseline is exact (a dark room's row means, say) and
        # the ratio is infinite, not 1e15 from rounding
        out[f"tonemapped_rmse_over_{b}"] = float(estimate["tonemapped_rmse"] / den) if den > 1e-12 else float("inf")
    return out


def with_baselines(estimate: dict, truth: np.ndarray, mask: np.ndarray) -> dict:
    """``estimate`` (a metrics dict) plus ``baselines`` ({constant, row_mean}: their metrics), ``skill``
    (:func:`skill`) and ``beats_row_mean`` ({ssim, tonemapped_rmse}: bool). Existing keys are left unchanged."""
    base = baseline_metrics(truth, mask)
    sk = skill(estimate, base)
    return {**estimate, "baselines": base, "skill": sk,
            "beats_row_mean": {"ssim": bool(sk["ssim_over_row_mean"] > 0),
                               "tonemapped_rmse": bool(sk["tonemapped_rmse_over_row_mean"] < 1)}}
