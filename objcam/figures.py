"""Figures a person would rather look at than read: matplotlib (Agg), written atomically as PNG."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from objcam.image_io import atomic_write_bytes, tonemap


def save_figure(fig, path: str | Path, dpi: int = 110) -> None:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def overview_figure(path: str | Path, target: np.ndarray, truth: np.ndarray | None, estimate: np.ndarray,
                    mask: np.ndarray, title: str = "") -> None:
    """Target photo | true envmap | recovered envmap (envmaps share the truth's exposure; texels the solve did
    not model are dimmed). Arrays: target (h, w, 3), envmaps (H, 2H, 3) linear radiance, mask (H, 2H) bool, of
    objcam's grid; drawn in the standard file convention (objcam.envmap.to_file)."""
    import matplotlib

    from objcam.envmap import to_file

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("target photo", tonemap(target)[0])]
    truth = None if truth is None else to_file(truth)
    estimate, mask = to_file(estimate), to_file(mask)
    ref = None
    if truth is not None:
        from objcam.metrics import tonemap_scale  # the scores' white (a flat background is not white)

        t, ref = tonemap(np.where(mask[..., None], truth, 0.0), tonemap_scale(truth, mask))
        panels.append(("true envmap (area-averaged)", t))
    e, ref = tonemap(estimate, ref)
    panels.append(("recovered envmap", e * np.where(mask[..., None], 1.0, 0.3)))
    widths = [p[1].shape[1] / p[1].shape[0] for p in panels]
    fig, axes = plt.subplots(1, len(panels), figsize=(2.6 * sum(widths), 2.9),
                             gridspec_kw={"width_ratios": widths})
    for ax, (name, img) in zip(np.atleast_1d(axes), panels):
        ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=9)
    fig.text(0.5, -0.02, f"tonemap: divide by the truth's white ({ref:.3g}, objcam.metrics.tonemap_scale), clip, "
             "gamma 1/2.2",
             ha="center", fontsize=7)
    save_figure(fig, path)
