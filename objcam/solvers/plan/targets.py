"""What the plan takes in and hands back per target: the fitted pixels and the solved envmap with its artifacts'
arrays. The solve stage loads the former and writes the latter; the plan neither reads nor writes files."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from objcam.envmap import EnvGrid


class TargetData(NamedTuple):
    """One target photo at its transport's rows.

    transport: its camera's objcam.transport.Transport (shared by the targets of one camera group).
    pooled: (H', W', 3) the target pooled to A's image grid; pooled_ok: (H', W') bool, usable pooled pixels.
    y: (M, 3) float64, the pooled target at A's rows (``transport.pixel_index``); use: (M,) bool, usable rows.
    """

    transport: Any
    pooled: np.ndarray
    pooled_ok: np.ndarray
    y: np.ndarray
    use: np.ndarray


@dataclass
class TargetSolution:
    """One target's result, as the solve stage writes it (data_layout.md, ``solve``).

    envmap: (H, W, 3) lat-long radiance, 0 where unsolved; mask: (H, W) bool, solved texels.
    prediction: (H', W', 3) the model's image; info: solve.json.
    albedo: (H', W', 3) the estimated albedo (0 where not estimated) and albedo_mask: (H', W') bool, where it was
    unknown and estimated; both None for a known albedo.
    fine: (envmap, mask) on a supersampled A's grid when ``envmap`` and ``mask`` are their area average.
    rejected: (M,) bool, A's rows the solve dropped as outliers (objcam.solvers.outliers); None when none were.
    profile: (N,) bool over A's texels, those the map gives as one value per row (objcam.solvers.skyprofile); None
    when the map is as solved.
    """

    envmap: np.ndarray
    mask: np.ndarray
    prediction: np.ndarray
    info: dict
    albedo: np.ndarray | None = None
    albedo_mask: np.ndarray | None = None
    fine: tuple[np.ndarray, np.ndarray] | None = None
    rejected: np.ndarray | None = None
    profile: np.ndarray | None = None


def texel_mask(grid: EnvGrid, texel_index: np.ndarray) -> np.ndarray:
    """(H, W) bool: the texels ``texel_index`` (flat into ``grid``) set."""
    mask = np.zeros(grid.n_texels, bool)
    mask[texel_index] = True
    return mask.reshape(grid.shape)
