"""Per-target numbers of the hard-case suite, from what ``objcam run`` wrote: evaluate's metrics.json (the envmap
metrics, the constant and row-mean baselines and the skill over them), the solve's envmap for the energy per
elevation band, stage.json for the A and solve times; and the truth's source contrast.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

BANDS = ((0.0, 10.0), (10.0, 30.0), (30.0, 60.0), (60.0, 90.0))  # elevation above the horizon, degrees
LUMA = np.array([0.2126, 0.7152, 0.0722])
EXCLUDE_TEXELS = 1  # the next source is looked for this many texels away from the brightest one's region


def _solid_angles(h: int) -> np.ndarray:
    t = np.linspace(0, np.pi, h + 1)
    return np.repeat(((np.cos(t[:-1]) - np.cos(t[1:])) * np.pi / h)[:, None], 2 * h, axis=1)


def band_energy_ratios(est: np.ndarray, truth: np.ndarray) -> list[float | None]:
    """Estimate / truth solid-angle energy (luminance x steradians) in each band of :data:`BANDS`, over every
    texel whose centre lies in the band (unsolved texels count as the 0 the solve wrote). est, truth: (H, 2H, 3)."""
    h = est.shape[0]
    elev = 90.0 - np.degrees(np.pi * (np.arange(h) + 0.5) / h)
    w = _solid_angles(h)
    le, lt = (est @ LUMA) * w, (truth @ LUMA) * w
    out = []
    for lo, hi in BANDS:
        rows = (elev >= lo) & (elev < hi)
        t = float(lt[rows].sum())
        out.append(float(le[rows].sum()) / t if t > 0 else None)
    return out


def below_horizon_energy(est: np.ndarray, truth: np.ndarray) -> float | None:
    """The estimate's solid-angle luminance energy in the rows wholly or mostly below the horizon (centre below
    it) over the truth's energy above: light the solve put where the plane hides the sky (issue 22, item 1).
    est, truth: (H, 2H, 3)."""
    h = est.shape[0]
    w = _solid_angles(h)
    up = float(((truth @ LUMA) * w)[: h // 2].sum())
    return float(((est @ LUMA) * w)[h // 2:].sum()) / up if up > 0 else None


def source_contrast(truth: np.ndarray) -> float:
    """Peak luminance of the truth's brightest source over that of the next one: the brightest texel's region
    (texels >= half its luminance, 8-connected, wrapping in azimuth) grown by :data:`EXCLUDE_TEXELS` is set aside
    and the brightest texel left is the next source. truth: (H, 2H, 3) on the solve's grid (upper half only)."""
    from scipy import ndimage

    lum = truth @ LUMA
    lum = lum[: lum.shape[0] // 2]  # sources above the horizon
    peak = float(lum.max())
    if peak <= 0:
        return 1.0
    w = lum.shape[1]
    tiled = np.concatenate([lum, lum, lum], axis=1)  # wrap in azimuth
    lab, _ = ndimage.label(tiled >= 0.5 * peak, structure=np.ones((3, 3)))
    r, c = np.unravel_index(int(np.argmax(lum)), lum.shape)
    region = lab == lab[r, c + w]
    region = ndimage.binary_dilation(region, np.ones((3, 3)), iterations=EXCLUDE_TEXELS)
    region = region[:, :w] | region[:, w:2 * w] | region[:, 2 * w:]
    rest = np.where(region, 0.0, lum)
    nxt = float(rest.max())
    return peak / nxt if nxt > 0 else float("inf")


def target_row(work: Path, capture: Path, target: str) -> dict:
    """The suite's numbers for one solved target (see the module docstring)."""
    from objcam.envmap import resample_to_height
    from objcam.image_io import read_exr

    m = json.loads((work / "evaluate" / "metrics.json").read_text())[target]
    est = read_exr(work / "solve" / target / "envmap.exr")[..., :3].astype(np.float64)
    truth = resample_to_height(read_exr(capture / m["truth_file"])[..., :3].astype(np.float64), est.shape[0])
    srec = json.loads((work / "solve" / "stage.json").read_text())
    trec = json.loads((work / "transport" / "stage.json").read_text())
    sm = srec["metrics"]["targets"][target]
    return {
        **{k: m.get(k) for k in ("ssim", "ssim_masked", "tonemapped_rmse", "relative_rmse",
                                 "relative_rmse_solid_angle", "brightest_angle_deg")},
        "baselines": m["baselines"], "skill": m["skill"], "beats_row_mean": m["beats_row_mean"],
        "band_energy": band_energy_ratios(est, truth),
        "below_horizon_energy": below_horizon_energy(est, truth),
        "source_contrast": source_contrast(truth),
        "a_seconds": trec["wall_seconds"], "a_summary": trec.get("summary", ""),
        "solve_seconds": sm.get("solve_seconds"),
        "transport_model": trec["metrics"].get("model"), "auto_margin": trec["metrics"].get("auto_margin"),
        "verdict": sm.get("verdict") or {},
    }
