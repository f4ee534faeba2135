"""PNG figures for the report: the singular spectrum, envmap-space maps (uncertainty) and image-space maps
(leverage, Cook's distance, gain images).

Figures are built on ``matplotlib.figure.Figure`` with the Agg canvas (no pyplot state, no display needed),
rendered to memory and written atomically with :func:`objcam.image_io.atomic_write_bytes`. NaN (texels or
pixels that are not part of the solve) is drawn light grey.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from objcam.analysis.spectrum import DEFAULT_RANK_TOL, effective_rank, entropy_effective_rank
from objcam.image_io import atomic_write_bytes

DPI = 110
BAD_COLOUR = "#d9d9d9"


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def _norm(values: np.ndarray, log: bool, signed: bool, vmin, vmax):
    from matplotlib.colors import LogNorm, Normalize, TwoSlopeNorm

    finite = values[np.isfinite(values)]
    if signed:
        lim = float(np.max(np.abs(finite))) if finite.size else 1.0
        lim = lim if lim > 0 else 1.0
        return TwoSlopeNorm(vcenter=0.0, vmin=-lim if vmin is None else vmin, vmax=lim if vmax is None else vmax)
    if log:
        pos = finite[finite > 0]
        lo = float(pos.min()) if pos.size else 1e-12
        hi = float(pos.max()) if pos.size else 1.0
        return LogNorm(vmin=lo if vmin is None else vmin, vmax=max(hi, lo * 1.0001) if vmax is None else vmax)
    lo = float(finite.min()) if finite.size else 0.0
    hi = float(finite.max()) if finite.size else 1.0
    return Normalize(vmin=lo if vmin is None else vmin, vmax=hi if vmax is None else vmax)


def _cmap(name: str):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad=BAD_COLOUR)


def plot_spectrum(sv: np.ndarray, path: str | Path, *, tol: float = DEFAULT_RANK_TOL, lr: float | None = None,
                  title: str = "Singular spectrum of A") -> Path:
    """Normalised singular values ``s_k / s_0`` on a log axis, the threshold ``tol`` and the effective rank
    (:func:`effective_rank`) marked, the entropy effective rank in the legend; with ``lr`` (absolute) also the
    ridge level ``sqrt(lr) / s_0`` below which modes are damped by more than half."""
    sv = np.asarray(sv, dtype=np.float64)
    s0 = float(sv.max()) if sv.size and sv.max() > 0 else 1.0
    rel = sv / s0
    r = effective_rank(sv, tol)
    er = entropy_effective_rank(sv)
    fig = _figure((6.4, 4.0))
    ax = fig.add_subplot()
    k = np.arange(1, sv.size + 1)
    shown = np.where(rel > 0, rel, np.nan)
    ax.semilogy(k, shown, lw=1.5, color="#1f77b4", label="s_k / s_1")
    ax.axhline(tol, color="#d62728", ls="--", lw=1, label=f"threshold {tol:g}")
    ax.axvline(r, color="#2ca02c", ls=":", lw=1.5, label=f"effective rank {r} (of {sv.size})")
    ax.plot([], [], " ", label=f"entropy effective rank {er:.1f}")
    if lr is not None and lr > 0:
        ax.axhline(np.sqrt(lr) / s0, color="#9467bd", ls="-.", lw=1, label="ridge level sqrt(lr) / s_1")
    ax.set_xlabel("index k")
    ax.set_ylabel("normalised singular value s_k / s_1")
    ax.set_title(title)
    floor = np.nanmin(shown) if np.isfinite(shown).any() else tol
    ax.set_ylim(max(min(floor, tol) / 2, 1e-12), 2.0)
    ax.set_xlim(0, max(sv.size, 1) + 1)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    return _save(fig, path)


def plot_envmap_map(values: np.ndarray, path: str | Path, *, title: str, units: str | None = None,
                    log: bool = False, cmap: str = "viridis", vmin=None, vmax=None) -> Path:
    """A per-texel map (H, 2H) of objcam's grid (e.g. :func:`objcam.analysis.to_grid` of
    :func:`texel_uncertainty`) drawn in the standard file convention (objcam.envmap.to_file): -x at both edges,
    +y a quarter from the left, +x at the centre, -y three quarters; polar angle 0 (zenith) .. 180 deg top to
    bottom. NaN texels (not kept) grey."""
    from objcam.envmap import to_file

    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2:
        raise ValueError(f"expected an (H, W) map, got {v.shape}")
    v = to_file(v)
    fig = _figure((7.0, 3.9))
    ax = fig.add_subplot()
    im = ax.imshow(np.ma.masked_invalid(v), cmap=_cmap(cmap), norm=_norm(v, log, False, vmin, vmax),
                   extent=(0.0, 360.0, 180.0, 0.0), aspect="auto", interpolation="nearest")
    ax.set_xlabel("direction (standard lat-long: u = 0.5 - atan2(y, x) / 360 deg)")
    ax.set_ylabel("polar angle theta [deg] (0 = zenith)")
    ax.set_xticks(np.arange(0, 361, 90), ["-x", "+y", "+x", "-y", "-x"])
    ax.set_yticks(np.arange(0, 181, 30))
    ax.set_title(title)
    cb = fig.colorbar(im, ax=ax)
    if units:
        cb.set_label(units)
    return _save(fig, path)


def plot_image_map(values: np.ndarray, path: str | Path, *, title: str, units: str | None = None,
                   log: bool = False, signed: bool = False, cmap: str | None = None, vmin=None,
                   vmax=None) -> Path:
    """A per-pixel map (H, W) of the (pooled) image (e.g. :func:`objcam.analysis.scatter_to_image` of the
    leverage or of a gain image) with a colour bar. ``signed`` uses a diverging map centred on 0 (gain images),
    ``log`` a log colour scale (non-positive values grey)."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2:
        raise ValueError(f"expected an (H, W) image, got {v.shape}")
    h, w = v.shape
    width = 6.4
    fig = _figure((width, max(2.5, min(8.0, width * h / max(w, 1) * 0.85 + 0.8))))
    ax = fig.add_subplot()
    im = ax.imshow(np.ma.masked_invalid(v), cmap=_cmap(cmap or ("RdBu_r" if signed else "viridis")),
                   norm=_norm(v, log and not signed, signed, vmin, vmax), interpolation="nearest")
    ax.set_xlabel("pixel column")
    ax.set_ylabel("pixel row")
    ax.set_title(title)
    cb = fig.colorbar(im, ax=ax, shrink=0.9)
    if units:
        cb.set_label(units)
    return _save(fig, path)


def plot_image_grid(images, path: str | Path, *, titles, suptitle: str | None = None, units: str | None = None,
                    signed: bool = True, ncols: int = 3) -> Path:
    """Several per-pixel maps (k, H, W) side by side, each with its own colour bar (gain images of several
    texels: ``signed`` diverging colour map centred on 0)."""
    imgs = [np.asarray(im, dtype=np.float64) for im in images]
    k = len(imgs)
    if k == 0:
        raise ValueError("no images")
    titles = list(titles)
    ncols = max(1, min(ncols, k))
    nrows = (k + ncols - 1) // ncols
    h, w = imgs[0].shape
    pw = 3.4
    fig = _figure((pw * ncols, nrows * max(2.0, pw * h / max(w, 1) * 0.85 + 0.6) + (0.4 if suptitle else 0)))
    for i, v in enumerate(imgs):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        im = ax.imshow(np.ma.masked_invalid(v), cmap=_cmap("RdBu_r" if signed else "viridis"),
                       norm=_norm(v, False, signed, None, None), interpolation="nearest")
        ax.set_title(titles[i] if i < len(titles) else "", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        cb.ax.tick_params(labelsize=7)
        if units:
            cb.set_label(units, fontsize=8)
    if suptitle:
        fig.suptitle(suptitle)
    return _save(fig, path)
