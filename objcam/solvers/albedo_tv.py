"""Edge-preserving albedo step: a total-variation albedo prior picks piecewise-constant regions, least squares
their values.

With the envmaps X held, each pixel's albedo enters the data term through its own quadratic (per channel c)

    sum_l (y_plc - rho_pc s_plc)^2 = w_pc (rho_pc - f_pc)^2 + const,   s_pl = (A' x_l)_p,  w_pc = sum_l s_plc^2,

``f_pc = sum_l y_plc s_plc / w_pc`` its least-squares albedo. A support is printed, painted or woven: its albedo is
piecewise constant, while whatever the envmap estimate gets wrong (a shadow too faint, a penumbra misplaced) a free
per-pixel albedo absorbs as low-contrast streaks, and the envmaps solved at that albedo then keep the error (on
the bench's dots scene the albedo's 0.4% error cost the envmap 0.09 SSIM against the true albedo). The step first
minimises

    sum_pc w_pc (u_pc - f_pc)^2 / 2 + lam sum_(i,j) ||u_i - u_j||_2,   rho_min <= u <= 1,

over the 4-neighbouring pairs (i, j) of estimated pixels on the image grid (vectorial TV: the channels share
their edges; the data term halved, i.e. the albedo step of the joint objective with a TV weight of 2 lam), by
the primal-dual algorithm of Chambolle and Pock (2011, Alg. 1). ``lam`` is set from a contrast:
``lam = contrast x median(rho) x median(w)``, so variations below about that fraction of the typical albedo,
over regions a few pixels across, are flattened while a print's edges (tens of percent) stay. Pixels not
estimated (held at a known albedo) are left as they are.

TV's known bias is a loss of contrast (a region's level moves by about lam x perimeter / (w x area): 2% of a dark
3-pixel dot's albedo here). So TV only picks the regions: neighbouring pixels whose TV albedos differ by less than
the contrast (x the median albedo) are joined, and each region gets the least-squares albedo of its pixels'
data, ``sum w f / sum w`` -- the data term's minimiser among albedos constant on those regions (a refitting or
"debiasing" of the TV estimate). Measured on the bench's dots scene: envmap SSIM 0.675 -> 0.710, the albedo's
relative error 0.0034 -> 0.0021; joining only regions flat to 0.1% / 0.2% / 0.3% / 0.6% / 1.2% of the albedo gave
0.667 / 0.699 / 0.708 / 0.710 / 0.709 (fragments that keep the streaks apart put them back).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from objcam.solvers.joint.albedo import albedo_normal
from objcam.solvers.joint.blocks import DEFAULT_RHO_MIN
from objcam.solvers.joint.kernels import matmul


@dataclass
class TVAlbedo:
    """Result of :func:`tv_albedo`: ``rho`` (M, C), the iterations run, the last relative change of rho, the
    number of grid edges, the absolute weight ``lam`` and the dual variable ``q`` (a warm start: the horizontal
    (H, W-1, C) and vertical (H-1, W, C) edges' parts)."""

    rho: np.ndarray
    iterations: int
    change: float
    edges: int
    lam: float
    q: tuple[np.ndarray, np.ndarray]
    regions: int | None = None  # regions refitted (None: no refit)


class ImageGraph:
    """The 4-neighbour pairs of estimated pixels on the image grid, as masks of the horizontal (H, W-1) and vertical
    (H-1, W) grid edges whose two pixels are both estimated; D and D^T by array slicing."""

    def __init__(self, pixel_index: np.ndarray, image_shape: tuple[int, int], free: np.ndarray):
        h, w = image_shape
        self.shape = (h, w)
        self.flat = np.asarray(pixel_index)  # (M,) flat index on the image of each row
        on = np.zeros(h * w, bool)
        on[self.flat[free]] = True
        on = on.reshape(h, w)
        self.on = on[..., None]  # (H, W, 1): estimated pixels
        self.mh = (on[:, :-1] & on[:, 1:])[..., None]
        self.mv = (on[:-1, :] & on[1:, :])[..., None]
        self.edges = int(self.mh.sum() + self.mv.sum())

    def regions(self, u: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
        """Connected regions of rows joined by graph edges across which ``u`` (M, C) changes by less than ``tol``
        (max over channels): (labels (M,), count). Rows off the graph are regions of their own."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        m = self.flat.size
        pos = np.full(self.shape[0] * self.shape[1], -1, np.int64)
        pos[self.flat] = np.arange(m)
        P = pos.reshape(self.shape)
        U = self.to_grid(u)
        ii, jj = [], []
        for a, b, ua, ub, on in ((P[:, :-1], P[:, 1:], U[:, :-1], U[:, 1:], self.mh[..., 0]),
                                 (P[:-1, :], P[1:, :], U[:-1, :], U[1:, :], self.mv[..., 0])):
            same = on & (np.abs(ua - ub).max(axis=2) < tol)
            ii.append(a[same])
            jj.append(b[same])
        ii, jj = np.concatenate(ii), np.concatenate(jj)
        n, labels = connected_components(coo_matrix((np.ones(ii.size), (ii, jj)), shape=(m, m)), directed=False)
        return labels, int(n)

    def to_grid(self, v: np.ndarray) -> np.ndarray:
        g = np.zeros((self.shape[0] * self.shape[1], v.shape[1]))
        g[self.flat] = v
        return g.reshape(*self.shape, v.shape[1])

    def from_grid(self, g: np.ndarray) -> np.ndarray:
        return g.reshape(-1, g.shape[2])[self.flat]

    def grad(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """D u on the grid (H, W, C) -> (horizontal, vertical) differences, 0 off the graph."""
        return (u[:, 1:] - u[:, :-1]) * self.mh, (u[1:, :] - u[:-1, :]) * self.mv

    def grad_t(self, qh: np.ndarray, qv: np.ndarray) -> np.ndarray:
        """D^T q on the grid (H, W, C)."""
        out = np.zeros((*self.shape, qh.shape[2]))
        out[:, :-1] -= qh
        out[:, 1:] += qh
        out[:-1, :] -= qv
        out[1:, :] += qv
        return out


def rof_graph(f: np.ndarray, w: np.ndarray, graph: ImageGraph, lam: float, free: np.ndarray,
              lo: float = DEFAULT_RHO_MIN, hi: float = 1.0, u0: np.ndarray | None = None,
              q0: tuple[np.ndarray, np.ndarray] | None = None, max_iter: int = 500,
              tol: float = 1e-6) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], int, float]:
    """min_u sum w (u - f)^2 / 2 + lam sum_e ||(D u)_e||, lo <= u <= hi on ``free`` rows (the others stay at f).

    f, w: (M, C) (w >= 0), rows on ``graph``. Chambolle-Pock (tau = 1 / median(w), sigma = 1 / (8 tau)); stops
    when u changes by less than ``tol`` relative. Returns (u, q, iterations, change)."""
    f = np.asarray(f, np.float64)
    C = f.shape[1]
    h, w_ = graph.shape
    if q0 is None:
        q0 = (np.zeros((h, w_ - 1, C)), np.zeros((h - 1, w_, C)))
    qh, qv = (np.array(a, np.float64) for a in q0)
    if lam <= 0 or graph.edges == 0:
        return np.where(free[:, None], np.clip(f, lo, hi), f), (qh, qv), 0, 0.0
    # steps scaled to the data weight (tau sigma ||D||^2 <= 1, ||D||^2 <= 8 on a 4-neighbour grid): tau w ~ 1 lets
    # the primal leave f in a few iterations whatever the units of w
    wf = np.where(free[:, None], w, 0.0)
    tau = 1.0 / max(float(np.median(wf[free])) if free.any() else 1.0, 1e-30)
    sigma = 1.0 / (8.0 * tau)
    F = graph.to_grid(f)
    W = graph.to_grid(wf)
    U = graph.to_grid(f if u0 is None else np.asarray(u0, np.float64))
    Ubar = U.copy()
    change, it = 0.0, 0
    for it in range(1, max_iter + 1):
        gh, gv = graph.grad(Ubar)
        qh += sigma * gh
        qv += sigma * gv
        qh /= np.maximum(1.0, np.sqrt(np.einsum("ijc,ijc->ij", qh, qh))[..., None] / lam)  # ||q_e|| <= lam
        qv /= np.maximum(1.0, np.sqrt(np.einsum("ijc,ijc->ij", qv, qv))[..., None] / lam)
        U_old = U
        U = (U - tau * graph.grad_t(qh, qv) + tau * W * F) / (1.0 + tau * W)
        U = np.where(graph.on, np.clip(U, lo, hi), F)
        Ubar = 2.0 * U - U_old
        change = _l2(U - U_old) / max(_l2(U), 1e-30)
        if change < tol:
            break
    return graph.from_grid(U), (qh, qv), it, change


def _l2(a: np.ndarray) -> float:
    """The Euclidean norm of ``a`` (any shape) without BLAS: np.linalg.norm's ddot wakes OpenBLAS's threads on
    every call (twice per Chambolle-Pock iteration, which runs outside single_blas_thread); on a loaded machine
    that was about half of the final step's time on a 128 px capture (issue 29, bench/results.md)."""
    v = np.ravel(a)
    return float(np.sqrt(np.einsum("i,i->", v, v)))


def tv_albedo(A: np.ndarray, Y: np.ndarray, X: np.ndarray, rho_prev: np.ndarray, fixed: np.ndarray,
              pixel_index: np.ndarray, image_shape: tuple[int, int], contrast: float,
              warm: TVAlbedo | None = None, rho_min: float = DEFAULT_RHO_MIN, refit: bool = True) -> TVAlbedo:
    """The albedo step with the TV prior (module docstring) for one camera at the envmaps X.

    A: (M, N) A' (albedo 1); Y: (M, L, C) photos; X: (N, L, C); rho_prev: (M, C) the current albedo (pixels
    ``fixed`` (M,) bool stay at it, as do never-lit pixels' least squares); pixel_index (M,) into image_shape.
    contrast: the prior's weight as a fraction of the median albedo (lam above); warm: a previous result for the
    same camera (its rho and dual start the iteration). refit: TV picks the regions, least squares their values
    (module docstring)."""
    S = matmul(A, X.reshape(X.shape[0], -1)).reshape(Y.shape)
    C = Y.shape[2]
    w = np.empty(rho_prev.shape)
    f = np.empty(rho_prev.shape)
    for c in range(C):
        a, beta = albedo_normal(S[:, :, c], Y[:, :, c], rho_prev[:, c])
        w[:, c], f[:, c] = a, beta / a
    free = ~np.asarray(fixed, bool)
    f[~free] = rho_prev[~free]
    graph = ImageGraph(pixel_index, image_shape, free)
    level = float(np.median(np.clip(f[free], rho_min, 1.0))) if free.any() else 0.0
    lam = contrast * float(np.median(w[free])) * level if free.any() else 0.0
    u, q, it, change = rof_graph(f, w, graph, lam, free, lo=rho_min, u0=None if warm is None else warm.rho,
                                 q0=None if warm is None else warm.q)
    regions = None
    if refit and lam > 0:
        labels, regions = graph.regions(u, contrast * level)
        u = refit_regions(u, f, w, labels, regions, free, rho_min)
    return TVAlbedo(u, it, change, graph.edges, lam, q, regions)


def refit_regions(u: np.ndarray, f: np.ndarray, w: np.ndarray, labels: np.ndarray, n: int, free: np.ndarray,
                  rho_min: float = DEFAULT_RHO_MIN) -> np.ndarray:
    """Each region's albedo set to its least squares ``sum w f / sum w`` (per channel, over its ``free`` pixels,
    clipped to [rho_min, 1]): the data term's minimiser among albedos constant on the regions. ``labels`` (M,) in
    [0, n); pixels not free keep ``u``."""
    out = np.array(u, np.float64)
    for c in range(u.shape[1]):
        num = np.bincount(labels, weights=np.where(free, w[:, c] * f[:, c], 0.0), minlength=n)
        den = np.bincount(labels, weights=np.where(free, w[:, c], 0.0), minlength=n)
        val = np.clip(num / np.where(den > 0, den, 1.0), rho_min, 1.0)
        out[:, c] = np.where(free & (den[labels] > 0), val[labels], out[:, c])
    return out
