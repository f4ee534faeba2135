"""Surfaces of uniform but unknown albedo: one albedo per channel shared by a group of pixels across cameras.

A one-colour object (a 3D print in one filament, a painted figurine) has one albedo, not one per pixel. With a free
albedo per pixel, each object pixel's albedo absorbs its own shading level and only the ratios of its values
across the illuminations constrain the envmap; the light a few degrees above the horizon, which reaches the
object's sides and barely the plane, then follows the object's albedo against the support's, which the data leave
nearly free (bench/results.md, session 49: the low sky 4-10x too bright). One shared albedo keeps the object's
shading pattern across its surface as data: how its sides compare with its top is what the low sky sets.

Group g's albedo ``a_gc`` enters the objective through every pixel i of the group as ``rho_ic = a_gc``. For fixed
envmaps the albedo problem of one channel is ``0.5 r^T H r - b^T r`` per camera (objcam.solvers.joint.problem
.rho_system); substituting ``r_i = a`` for the group's pixels makes a's part the 1-D quadratic
``0.5 a^2 sum_k 1^T H_gg 1 - a sum_k (1^T b_g - 1^T H_gf r_f)`` (f: the camera's other pixels, held), minimised
over [rho_min, 1] in closed form (:func:`group_values`). Without an albedo prior (lp = 0) H is diagonal, the group
decouples from every other pixel and the rho-step stays exact; with one, the rho-step is one block-coordinate pass
(the other pixels at the group's value, then the group at theirs), which still cannot raise the objective.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def check_groups(groups, m: int, fixed: np.ndarray, k: int) -> np.ndarray:
    """Camera k's group labels as an (M,) int64 array (zeros for None), checked against its ``fixed`` mask."""
    if groups is None:
        return np.zeros(m, np.int64)
    g = np.asarray(groups).ravel()
    if g.shape != (m,) or not np.issubdtype(g.dtype, np.integer):
        raise ValueError(f"camera {k}: groups must be {m} integers (one per row of A'), got {g.dtype} {g.shape}")
    if (g < 0).any():
        raise ValueError(f"camera {k}: group labels must be >= 0 (0: the pixel's own albedo)")
    if (fixed & (g > 0)).any():
        raise ValueError(f"camera {k}: a pixel of known albedo (fixed) cannot be in a group")
    return g.astype(np.int64)


def unify(rho: list[np.ndarray], groups: list[np.ndarray], ids: np.ndarray, rho_min: float) -> list[np.ndarray]:
    """Give every group's pixels the mean of their albedos, per channel, over all cameras (in place; rho: per
    camera (M_p, C)); returns rho."""
    for g in ids:
        sel = [gr == g for gr in groups]
        n = sum(int(s.sum()) for s in sel)
        if n == 0:
            continue
        mean = sum(r[s].sum(axis=0) for r, s in zip(rho, sel)) / n
        for r, s in zip(rho, sel):
            r[s] = np.clip(mean, rho_min, 1.0)
    return rho


def group_values(parts: dict[int, list[tuple[float, float]]], current: dict[int, float], rho_min: float
                 ) -> dict[int, float]:
    """Each group's minimiser of its 1-D quadratic over [rho_min, 1]: ``parts[g]``: per camera (1^T H_gg 1,
    1^T b_g - 1^T H_gf r_f); a group no camera's data sees (curvature 0) keeps ``current[g]``."""
    out = {}
    for g, terms in parts.items():
        h, b = _summed(terms)
        out[g] = float(np.clip(b / h, rho_min, 1.0)) if h > 0 else current[g]
    return out


def _summed(terms: list[tuple[float, float]]) -> tuple[float, float]:
    """A group's 1-D quadratic over every camera: its cameras' (curvature, linear term) summed."""
    return float(sum(t[0] for t in terms)), float(sum(t[1] for t in terms))


def group_terms(H: sp.csr_matrix, b: np.ndarray, r: np.ndarray, sel: np.ndarray) -> tuple[float, float]:
    """One camera's part of a group's 1-D quadratic: (1^T H_gg 1, 1^T b_g - 1^T H_gf r_f) for the group's pixels
    ``sel`` (M,) bool at the other pixels' albedo r (M,) (H: the camera's albedo system, b its right-hand side)."""
    Hg = H[sel]
    other = np.where(sel, 0.0, r)
    return float(Hg[:, sel].sum()), float(b[sel].sum() - (Hg @ other).sum())


def group_kkt(parts: dict[int, list[tuple[float, float]]], values: dict[int, float], rho_min: float,
              scale: float) -> float:
    """The largest relative KKT residual of the groups' 1-D problems at ``values`` (as objcam.solvers.joint.boxqp
    .box_kkt_residual: the natural residual in units of ``scale``, the largest |b| of the cameras' systems)."""
    worst = 0.0
    for g, terms in parts.items():
        h, b = _summed(terms)
        if h <= 0:
            continue
        a = values[g]
        grad = h * a - b
        worst = max(worst, h * abs(a - float(np.clip(a - grad / h, rho_min, 1.0))))
    return worst / scale if scale > 0 else worst


def labels(groups: list[np.ndarray | None]) -> set[int]:
    """The group labels (> 0) used by any camera."""
    return {int(g) for gr in groups if gr is not None for g in np.unique(gr[gr > 0])}


def values_of(rho: list[np.ndarray], groups: list[np.ndarray | None]) -> dict[int, np.ndarray]:
    """{group: its albedo (C,)} read from the first of its pixels (rho: per camera (M_p, C))."""
    out: dict[int, np.ndarray] = {}
    for r, gr in zip(rho, groups):
        if gr is None:
            continue
        for g in np.unique(gr[gr > 0]):
            out.setdefault(int(g), np.array(r[np.flatnonzero(gr == g)[0]], np.float64))
    return out


def set_values(rho: list[np.ndarray], groups: list[np.ndarray | None], values: dict[int, np.ndarray]
               ) -> list[np.ndarray]:
    """Give each group's pixels its value in ``values`` (in place); returns rho."""
    for r, gr in zip(rho, groups):
        if gr is None:
            continue
        for g, v in values.items():
            r[gr == g] = v
    return rho


def least_squares_values(As: list[np.ndarray], Ys: list[np.ndarray], X: np.ndarray, groups: list[np.ndarray | None],
                         rho_min: float) -> dict[int, np.ndarray]:
    """{group: (C,)} each group's albedo by least squares over all its pixels and the L targets at the envmaps X
    (N, L, C), without an albedo prior: ``sum_i beta_i / sum_i a_i`` (objcam.solvers.joint.albedo.albedo_normal's
    terms), clipped to [rho_min, 1]. As: per camera A' (M_p, N); Ys: (M_p, L, C)."""
    from objcam.solvers.joint.albedo import albedo_normal
    from objcam.solvers.joint.kernels import matmul

    num: dict[int, np.ndarray] = {}
    den: dict[int, np.ndarray] = {}
    for A, Y, gr in zip(As, Ys, groups):
        if gr is None or not (gr > 0).any():
            continue
        S = matmul(A, X.reshape(X.shape[0], -1)).reshape(Y.shape)
        terms = [albedo_normal(S[:, :, c], Y[:, :, c], None) for c in range(Y.shape[2])]  # (a, beta) per channel
        for g in np.unique(gr[gr > 0]):
            sel = gr == g
            num[int(g)] = num.get(int(g), 0.0) + np.array([b[sel].sum() for _, b in terms])
            den[int(g)] = den.get(int(g), 0.0) + np.array([a[sel].sum() for a, _ in terms])
    return {g: np.clip(num[g] / np.where(den[g] > 0, den[g], 1.0), rho_min, 1.0) for g in num}
