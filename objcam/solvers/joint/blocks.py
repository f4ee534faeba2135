"""The inputs of the joint solve: one camera's data (:class:`CameraBlock`), its albedo graph, the albedo defaults.

Albedo regulariser G ("the regularised inverse" of the method). We read it as a Tikhonov-regularised inverse for
rho: the albedo is found by inverting the shading with a quadratic smoothness prior, i.e. ``G_p`` is the
first-difference (gradient) operator on camera p's image grid: one row ``rho_i - rho_j`` per pair of
4-neighbouring valid pixels (i, j) (same row, adjacent columns, or same column, adjacent rows), built from
``pixel_index`` (flat ``r * W + c``) and ``image_shape`` (H, W) by :func:`albedo_smoothness_operator`. So
``lp ||G rho||^2`` is the discrete Dirichlet energy of the albedo image; albedo edges cost in proportion to their
squared contrast. There are no edges between cameras. ``lp = 0`` (default) drops the term and makes the albedo
step closed form.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

#: Default lower bound on the albedo (the model's (0, 1] made closed).
DEFAULT_RHO_MIN = 1e-3
#: Default initial albedo: mid-range, so that the first albedo step rarely clips at 1.
DEFAULT_RHO0 = 0.5


class NoValidPixelsError(ValueError):
    """The joint solve was given no valid pixel at all (M = 0 in every camera)."""


@dataclass
class CameraBlock:
    """One camera's data for :func:`objcam.solvers.joint.solve_joint`.

    A: (M, N) float32/64 rho-free light transport (valid pixels x kept texels), not copied.
    Y: (M, L, C) pixel values per target (illumination) and channel; (M, L) means C = 1, (M,) means L = C = 1.
    pixel_index: (M,) flat indices ``r * W + c`` of the valid pixels on ``image_shape`` (needed when lp > 0).
    image_shape: (H, W) of the camera's image.
    rho0: initial albedo, (M, C), (M,) or a scalar; default :data:`DEFAULT_RHO0`.
    fixed: (M,) bool, pixels whose albedo is known: held at rho0 (clipped into [rho_min, 1]), not estimated. Any
        fixed pixel pins the scale that c rho, x / c otherwise leaves free.
    groups: (M,) int, 0 for a pixel with an albedo of its own; g > 0 for the pixels of one surface of uniform but
        unknown albedo (a one-colour object): every pixel of group g, in every camera, shares one albedo per
        channel (:mod:`objcam.solvers.joint.groups`). Not with ``fixed``.
    """

    A: np.ndarray
    Y: np.ndarray
    pixel_index: np.ndarray | None = None
    image_shape: tuple[int, int] | None = None
    rho0: np.ndarray | float | None = None
    fixed: np.ndarray | None = None
    groups: np.ndarray | None = None


def as_camera_block(b: CameraBlock | Sequence) -> CameraBlock:
    """``b`` itself, or the CameraBlock of a tuple ``(A', Y[, pixel_index, image_shape, rho0, fixed, groups])``."""
    if isinstance(b, CameraBlock):
        return b
    return CameraBlock(*b)


def photos_mlc(Y: np.ndarray) -> np.ndarray:
    """Y as float64 (M, L, C): (M,) is one target and channel, (M, L) one channel."""
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim == 1:
        return Y[:, None, None]
    if Y.ndim == 2:
        return Y[:, :, None]
    if Y.ndim == 3:
        return Y
    raise ValueError(f"Y must be (M,), (M, L) or (M, L, C), got {Y.shape}")


def albedo_smoothness_operator(pixel_index: np.ndarray, image_shape: tuple[int, int]) -> sp.csr_matrix:
    """The albedo regulariser G: first differences between 4-neighbouring valid pixels of one image.

    pixel_index: (M,) flat indices ``r * W + c`` of the valid pixels (the row order of A'), unique;
    image_shape: (H, W). Returns G (E, M) csr float64 with one row ``rho_i - rho_j`` per horizontally
    ((r, c)-(r, c+1)) or vertically ((r, c)-(r+1, c)) adjacent pair of valid pixels; no wrap-around.
    ``||G rho||^2`` is the discrete Dirichlet energy of the albedo image; ``G^T G`` is its graph Laplacian.
    """
    pixel_index = np.asarray(pixel_index, dtype=np.int64).ravel()
    h, w = (int(v) for v in image_shape)
    m = pixel_index.size
    if m and (pixel_index.min() < 0 or pixel_index.max() >= h * w):
        raise ValueError(f"pixel_index out of range for a {h}x{w} image")
    if np.unique(pixel_index).size != m:
        raise ValueError("pixel_index holds duplicate pixels")
    row_of = np.full(h * w, -1, dtype=np.int64)
    row_of[pixel_index] = np.arange(m)
    row_of = row_of.reshape(h, w)
    i = np.concatenate([row_of[:, :-1].ravel(), row_of[:-1, :].ravel()])
    j = np.concatenate([row_of[:, 1:].ravel(), row_of[1:, :].ravel()])
    keep = (i >= 0) & (j >= 0)
    i, j = i[keep], j[keep]
    e = i.size
    rows = np.repeat(np.arange(e), 2)
    cols = np.stack([i, j], axis=1).ravel()
    vals = np.tile([1.0, -1.0], e)
    return sp.csr_matrix((vals, (rows, cols)), shape=(e, m))

