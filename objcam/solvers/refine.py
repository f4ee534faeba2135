"""Supersampled solves: A built on a grid ``s`` times finer than the envmap asked for, solved on an adaptive basis.

A box texel of the output grid is not one light: the radiance inside it varies (a sun, a tree line), and where
inside the texel the light comes from moves the shadows it casts. At 32 x 64 that discretisation is most of the
model error on the bench's targets (bench/results.md). With ``transport.supersample = 2`` the transport builds A
on the 2x finer grid and the solve recovers the envmap on a basis that is

* the output grid's texels (each the union of its s x s fine texels, merged at the poles like
  :func:`objcam.solvers.basis.texel_basis`) over most of the sphere, and
* the fine texels themselves inside the ``fraction`` of output texels with the most contrast in a pilot solve
  (tonemapped edge heights, where sub-texel structure moves the shadows most),

then area-averages the result back to the output grid (:func:`average_to`). Everything runs through the merged
basis machinery: the objective is the fine grid's, restricted to envmaps constant on each group.
Measured on the bench's four HDRIs (bench/results.md, session 12) at 32 x 64 output, against the default A:
SSIM forest / courtyard / city / sunrise 0.772 / 0.856 / 0.831 / 0.723 -> 0.807 / 0.828 / 0.837 / 0.777, relative
RMSE sunrise 3.66 -> 1.35, for 2.9x the A time and 3-4x the solve time.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from objcam.envmap import EnvGrid, area_downsample
from objcam.solvers.basis import texel_basis
from objcam.solvers.regularization import difference_operator


def coarse_of(fine: EnvGrid, texel_index: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The output texel of each fine texel: (coarse_index (N_c,) sorted flat indices on the ``height`` grid,
    member (N,) position of each fine texel's output texel in coarse_index)."""
    if fine.height % height:
        raise ValueError(f"envmap height {fine.height} is not a multiple of {height}")
    s = fine.height // height
    t = np.asarray(texel_index, dtype=np.int64).ravel()
    r, c = t // fine.width, t % fine.width
    coarse = (r // s) * (2 * height) + c // s
    idx, member = np.unique(coarse, return_inverse=True)
    return idx, member.ravel()


def _group_ids(P: sp.spmatrix | None, n: int) -> np.ndarray:
    return np.arange(n) if P is None else np.asarray(sp.csr_matrix(P).argmax(axis=1)).ravel()


def refined_basis(fine: EnvGrid, texel_index: np.ndarray, height: int, split: np.ndarray,
                  group: float) -> sp.csr_matrix:
    """(N, N') 0/1 basis over the fine kept texels: one unknown per output texel (output-grid groups of size
    ``group``), except the output texels flagged in ``split`` (N_c,) bool, whose fine texels get one unknown each
    (fine-grid groups of size ``group``)."""
    t = np.asarray(texel_index, dtype=np.int64).ravel()
    cidx, member = coarse_of(fine, t, height)
    coarse_gid = _group_ids(texel_basis(EnvGrid(height), cidx, group), cidx.size)[member]
    fine_gid = _group_ids(texel_basis(fine, t, group), t.size)
    key = np.where(np.asarray(split, bool)[member], cidx.size + fine_gid, coarse_gid)
    _, gid = np.unique(key, return_inverse=True)
    gid = gid.ravel()
    return sp.csr_matrix((np.ones(t.size), (np.arange(t.size), gid)), shape=(t.size, int(gid.max()) + 1))


def contrast(fine: EnvGrid, texel_index: np.ndarray, height: int, X: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    """(N_c,) per output texel: the summed heights of its edges in the tonemapped (power 1/gamma) luminance of
    the area-averaged X (N, C) -- where a pilot solve sees structure."""
    cidx, member = coarse_of(fine, texel_index, height)
    w = fine.solid_angles().ravel()[np.asarray(texel_index).ravel()]
    lum = np.maximum(np.asarray(X, float).reshape(len(member), -1).mean(axis=1), 0.0)
    mean = np.bincount(member, w * lum, cidx.size) / np.bincount(member, w, cidx.size)
    D = difference_operator(EnvGrid(height), cidx)
    e = np.abs(D @ (mean / max(float(mean.max()), 1e-30)) ** (1.0 / gamma))
    return np.asarray(abs(D).T @ e).ravel()


def split_by_contrast(scores: np.ndarray, fraction: float) -> np.ndarray:
    """(N_c,) bool: the ``fraction`` of output texels with the highest scores (ties broken by order)."""
    k = int(round(np.clip(fraction, 0.0, 1.0) * scores.size))
    split = np.zeros(scores.size, bool)
    if k:
        split[np.argsort(-scores, kind="stable")[:k]] = True
    return split


def average_to(env: np.ndarray, mask: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-average a fine envmap (H, 2H, C) over its kept texels ``mask`` (H, 2H) to ``height`` rows: (env_out
    (height, 2 height, C) radiance, mask_out: output texels holding at least one kept fine texel)."""
    # the solid-angle mean of env x mask over the mean of mask: the mean over the kept texels only
    m = np.asarray(mask, np.float64)
    num = area_downsample(env * m[..., None], height)
    den = area_downsample(m, height)
    out = np.where(den[..., None] > 0, num / np.maximum(den, 1e-300)[..., None], 0.0)
    return out.astype(env.dtype), den > 0
