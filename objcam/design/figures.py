"""Figures of ``objcam design``: per occluder its uncertainty and leverage maps (PNG, on the colour scales
shared by all occluders), and one side-by-side comparison figure: a row per occluder with the camera's view of
it, its uncertainty map and its leverage map, every uncertainty map on one log colour scale and every leverage
map on another, so colours compare across rows."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from objcam.analysis import plot_envmap_map, plot_image_map
from objcam.analysis.plots import BAD_COLOUR, DPI
from objcam.design.scoring import Scores
from objcam.envmap import to_file
from objcam.image_io import atomic_write_bytes

UNC_UNITS = "radiance per unit pixel noise"


def shared_limits(maps: list[np.ndarray], floor: float = 1e-12) -> tuple[float, float]:
    """(vmin, vmax) of the positive finite values of all ``maps``: one log colour scale for them all."""
    vals = np.concatenate([m[np.isfinite(m) & (m > floor)].ravel() for m in maps] + [np.empty(0)])
    if vals.size == 0:
        return 1e-3, 1.0
    lo, hi = float(vals.min()), float(vals.max())
    return lo, max(hi, lo * 1.0001)


def write_object_pngs(folder: Path, name: str, sc: Scores, unc_lim: tuple[float, float],
                      lev_lim: tuple[float, float]) -> None:
    """``folder/uncertainty.png`` (envmap grid) and ``folder/leverage.png`` (image) of one occluder."""
    plot_envmap_map(sc.uncertainty, folder / "uncertainty.png", log=True, vmin=unc_lim[0], vmax=unc_lim[1],
                    title=f"{name}: per-texel uncertainty sqrt(diag((A^T A + lr I)^-1))", units=UNC_UNITS)
    plot_image_map(sc.leverage, folder / "leverage.png", log=True, vmin=lev_lim[0], vmax=lev_lim[1],
                   title=f"{name}: leverage h_ii per pixel", units="h_ii")


def comparison_figure(path: Path, names: list[str], scores: list[Scores], unc_lim: tuple[float, float],
                      lev_lim: tuple[float, float], horizon_deg: float, zenith_deg: float) -> Path:
    """The side-by-side PNG: one row per occluder (view | uncertainty over the upper hemisphere, elevation 0 at
    the bottom | leverage), shared colour scales, the zenith and horizon band limits drawn on the uncertainty
    maps."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    n = len(scores)
    fig = Figure(figsize=(14.0, 2.9 * n + 0.9), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(n, 3, width_ratios=[1.0, 2.0, 1.0])
    unc_norm, lev_norm = LogNorm(*unc_lim), LogNorm(*lev_lim)
    cm_u = matplotlib.colormaps["viridis"].with_extremes(bad=BAD_COLOUR)
    cm_h = matplotlib.colormaps["magma"].with_extremes(bad=BAD_COLOUR)
    im_u = im_h = None
    for i, (name, sc) in enumerate(zip(names, scores)):
        k = sc.numbers
        ax = fig.add_subplot(gs[i, 0])
        ax.imshow(np.ma.masked_invalid(sc.view), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(f"{name}: camera view (occluder white)", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        ax = fig.add_subplot(gs[i, 1])
        # the lower half lies below the plane; drawn in the standard lat-long file convention
        upper = to_file(sc.uncertainty)[: sc.uncertainty.shape[0] // 2]
        im_u = ax.imshow(np.ma.masked_invalid(upper), cmap=cm_u, norm=unc_norm, aspect="auto",
                         extent=(0.0, 360.0, 0.0, 90.0), interpolation="nearest")
        for elev, style in ((zenith_deg, ":"), (horizon_deg, "--")):
            ax.axhline(elev, color="white", lw=0.8, ls=style)
        ax.set_xticks(np.arange(0, 361, 90), ["-x", "+y", "+x", "-y", "-x"])
        ax.set_yticks(np.arange(0, 91, 15))
        ax.set_ylabel("elevation [deg]", fontsize=8)
        if i == n - 1:
            ax.set_xlabel("direction (standard lat-long: u = 0.5 - atan2(y, x) / 360 deg)", fontsize=8)
        ax.set_title(f"{name}: uncertainty, upper sky mean {k['uncertainty_mean']:.3g}, worst "
                     f"{k['uncertainty_worst']:.3g} (spread {k['spread']:.2f}); zenith {k['uncertainty_zenith']:.3g}"
                     f", horizon {k['uncertainty_horizon']:.3g}", fontsize=9)
        ax = fig.add_subplot(gs[i, 2])
        im_h = ax.imshow(np.ma.masked_invalid(sc.leverage), cmap=cm_h, norm=lev_norm, interpolation="nearest")
        ax.set_title(f"{name}: leverage h_ii (sum {k['leverage_sum']:.0f})", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im_u, ax=[a for a in fig.axes[1::3]], shrink=0.6, location="bottom",
                 label=f"uncertainty ({UNC_UNITS}, log; one scale for all rows)")
    fig.colorbar(im_h, ax=[a for a in fig.axes[2::3]], shrink=0.8, location="bottom",
                 label="leverage h_ii (log; one scale for all rows)")
    fig.suptitle("Occluder design: which directions each object-camera resolves (lower uncertainty is better); "
                 f"lines: zenith band (elev >= {zenith_deg:g}, dotted), horizon band (elev < {horizon_deg:g}, "
                 "dashed)", fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)
