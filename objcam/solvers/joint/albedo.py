"""The albedo of each pixel by least squares over the targets, for fixed envmaps (no albedo prior).

For fixed x, with the shading ``s_il = (A' x_lc)_i`` of pixel i in target l, the albedo data term of one channel
is per pixel the 1-D quadratic ``a_i rho_i^2 - 2 beta_i rho_i`` with ``a_i = sum_l s_il^2`` and
``beta_i = sum_l s_il y_il`` (:func:`albedo_normal`). Without an albedo prior (lp = 0) the exact albedo step is
then ``rho_i = clip(beta_i / a_i, rho_min, 1)`` (:func:`albedo_at`); with one it is a sparse box QP
(:mod:`objcam.solvers.joint.rho_step`).
"""

from __future__ import annotations

import numpy as np

from objcam.solvers.joint.blocks import DEFAULT_RHO_MIN
from objcam.solvers.joint.kernels import matmul


def albedo_normal(s: np.ndarray, y: np.ndarray, rho_prev: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the 1-D albedo least squares over the L targets of one channel, ``a r^2 - 2 beta r``: (a, beta),
    each (M,), from the shading s (M, L) and the photos y (M, L). With ``rho_prev`` a pixel that is (almost) never
    lit gets a proximal term that holds it at its previous albedo."""
    a = np.einsum("ml,ml->m", s, s)
    beta = np.einsum("ml,ml->m", s, y)
    if rho_prev is not None:
        amax = float(a.max()) if a.size else 0.0
        delta = 1e-12 * amax if amax > 0 else 1.0
        weak = a <= delta
        a = a + np.where(weak, delta, 0.0)
        beta = beta + np.where(weak, delta * rho_prev, 0.0)
    return a, beta


def albedo_at(A: np.ndarray, Y: np.ndarray, X: np.ndarray, rho_prev: np.ndarray, fixed: np.ndarray | None = None,
              rho_min: float = DEFAULT_RHO_MIN) -> np.ndarray:
    """The exact albedo step without an albedo prior (lp = 0) for one camera at the envmaps X: per pixel and
    channel ``clip(beta / a, rho_min, 1)`` (the rule of :meth:`objcam.solvers.joint.problem.JointProblem.
    rho_system`, a never-lit pixel kept at ``rho_prev``), pixels ``fixed`` held at ``rho_prev``.

    A: (M, N) A' (float32 is converted in row blocks); Y: (M, L, C) photos; X: (N, L, C); rho_prev: (M, C).
    Returns (M, C)."""
    S = matmul(A, X.reshape(X.shape[0], -1)).reshape(Y.shape)
    rho = np.empty(rho_prev.shape)
    for c in range(Y.shape[2]):
        a, beta = albedo_normal(S[:, :, c], Y[:, :, c], rho_prev[:, c])
        rho[:, c] = np.clip(beta / a, rho_min, 1.0)
    if fixed is not None:
        rho[fixed] = rho_prev[fixed]
    return rho

