"""Joint recovery of the albedo and the environment maps (unknown albedo, several illuminations, several cameras).

Model. Camera p (p = 1..P) sees M_p valid pixels; its rho-free light transport is ``A'_p`` (M_p, N) (the same N
kept envmap texels for every camera) and its per-pixel albedo ``rho_p`` (M_p, C), one value per colour channel.
The photo of target (illumination) l in channel c is ``y_plc = diag(rho_pc) A'_p x_lc`` with ``x_lc`` (N,) the
envmap radiance. Colour channels never interact (rho, x and y are all per channel; only the grey A' is shared),
so everything below is per channel c; the objective reported is the sum over channels:

    F_c(rho, x) = sum_{p,l} ||diag(rho_pc) A'_p x_lc - y_plc||^2                      (data)
                + sum_l ( ls ||D x_lc||^2 + lr ||x_lc||^2 )                             (envmap prior)
                + lp sum_p ||G_p rho_pc||^2                                              (albedo prior)
      subject to  x_lc >= 0,   rho_min <= rho_pc <= 1.

Albedo regulariser G ("the regularised inverse" of the method). We read it as a Tikhonov-regularised inverse for
rho: the albedo is found by inverting the shading with a quadratic smoothness prior, i.e. ``G_p`` is the
first-difference (gradient) operator on camera p's image grid: one row ``rho_i - rho_j`` per pair of
4-neighbouring valid pixels (i, j) (same row, adjacent columns, or same column, adjacent rows), built from
``pixel_index`` (flat ``r * W + c``) and ``image_shape`` (H, W) by :func:`albedo_smoothness_operator`. So
``lp ||G rho||^2`` is the discrete Dirichlet energy of the albedo image; albedo edges cost in proportion to their
squared contrast. There are no edges between cameras. ``lp = 0`` (default) drops the term and makes the albedo
step closed form.

Edge-preserving envmap prior (``prior="edges"``; the solve stage's default). The quadratic ``ls ||D x_lc||^2``
charges an envmap edge by its squared height and smears every edge the shadows cannot pin down (a sun, a tree
line). The edge prior is the Huber penalty of :mod:`objcam.solvers.edges` on each target's edges, shared by the
colour channels:

    sum_l [ ls s_l 2 C sum_e huber_eps_l(r_le) ] + lr sum_lc ||x_lc||^2,   r_le = sqrt(mean_c (D x_lc)_e^2),

with ``s_l`` the RMS edge height of target l's envmap after the first x-step (which uses the quadratic prior) and
``eps_l = edge_eps s_l``; both are then fixed, so F is one fixed function from that point on (the histories start
there). Near r = s_l the penalty has the quadratic prior's slope, so ``ls`` keeps its meaning. The channels are
coupled only through r_le, and the penalty is handled by majorise-minimise inside the alternation: at the current
point X' the Huber is replaced by its quadratic majoriser, i.e. the quadratic prior with per-edge weights
``W_le = s_l / max(r_le(X'), eps_l)`` (equal to F at X', above it elsewhere). That majoriser is again separable per
channel, so every per-channel block step below applies unchanged, and a step that lowers the majoriser lowers F.
The weights are moved to the current point after every block that changes x (subspace proposal, scale step,
x-step); the x-step is followed by ``edge_steps - 1`` more majorise-minimise x-steps on the same Gram matrices
(factorisations only). The scale step minimises the true Huber objective. So F is non-increasing after every
sub-step, as with the quadratic prior.

Weights. ``ls`` and ``lr`` are relative to ``s' = mean(diag(sum_p A'_p^T A'_p))``, the data scale of the
transport at albedo 1 (the largest the albedo may be) -- the convention of :mod:`objcam.solvers.regularization`
applied to A' instead of diag(rho) A'. (A known-albedo solve with ``A = diag(rho) A'`` and relative weight w uses
the absolute weight ``w * mean(diag(A^T A))``, which is ``w * mean(rho^2)`` x ours, roughly.) ``lp`` is relative
to ``t = mean over pixels and channels of sum_l y_plc^2``, the curvature of the albedo data term at rho = 1
(the curvature at rho is ``t / rho^2``), so ``lp = 1`` ties each albedo to its neighbours as strongly as the
data ties it to its own value at rho = 1. ``relative=False`` takes all three as absolute weights.

Exact alternation (``method="exact"``): block-coordinate descent, each block solved exactly, so the objective is
non-increasing (``JointResult.step_history`` records it after every sub-step):

1. x-step: for fixed rho every x_lc solves the convex QP ``min x^T Q_lc x - 2 b_lc^T x, x >= 0`` with one
   Gram matrix per channel ``G_c = sum_p A'_p^T diag(rho_pc^2) A'_p``, shared by the L targets (and by the
   channels while the albedo is grey, as at the start), ``Q_lc = G_c + ls D^T W_l D + lr I`` (W_l = 1 for the
   quadratic prior: then one Q_c and one factorisation serve all targets) and ``b_lc = sum_p A'_p^T (rho_pc *
   y_plc)``; solved by :func:`objcam.solvers.nnls.solve_exact` (warm-started from the previous free set).
   Forming G_c (2 M N^2 flops per channel) is the dominant cost; the Gram matrices of one albedo are cached for
   the sweep (majorise-minimise x-steps, the final step).
2. rho-step: for fixed x, with ``s_pil = (A'_p x_lc)_i``, the albedo problem is
   ``min rho^T H rho - 2 beta^T rho`` over the box, ``H = diag(a) + lp G^T G``, ``a_i = sum_l s_il^2``,
   ``beta_i = sum_l s_il y_il``. With lp = 0 it is separable: ``rho_i = clip(beta_i / a_i, rho_min, 1)``. With
   lp > 0 it is a sparse strictly convex box-constrained QP per camera, solved exactly by :func:`solve_box_qp`
   (block principal pivoting for box constraints with sparse LU factorisations of the free block; its KKT
   residual is checked). A pixel with ``a_i ~ 0`` (its predicted shading is zero in every target, so the data
   does not see its albedo) gets a proximal term ``delta (rho_i - rho_i^prev)^2`` with ``delta = 1e-12 max(a)``:
   it keeps its previous value when nothing else determines it, and the step still cannot increase F.
3. scale step: the data term is invariant under ``(rho, x) -> (c rho, x / c)``; the regularisers are not. The
   objective at ``(clip(c rho, rho_min, 1), x / c)`` is minimised over c > 0: between the clips only
   ``c^2 lp sum||G rho||^2 + c^-2 sum_l (ls ||Dx||^2 + lr ||x||^2)`` varies (closed-form minimiser); beyond
   them the few pixels pushed past 1 stay at 1 and their data term changes. The 1-D function is scanned on a
   log grid and refined by golden-section search; c = 1 is a candidate, so the step never increases F. Without
   it the alternation crawls along the nearly flat scale valley.

The loop is x, then {rho, scale, x} until every channel's relative objective decrease over one sweep is below
``tol`` or ``max_iter`` sweeps; ending on an x-step makes the returned x exactly optimal for the returned rho
(``kkt_x`` ~ 1e-10) while ``kkt_rho`` measures how far the alternation still is from a stationary point.

Speed. Plain alternation is slow here: a smooth change of the albedo can be traded against a change of the
envmaps almost for free, and exact block steps crawl along that valley (rate 0.92-0.99 per sweep on test scenes;
hundreds of sweeps at N = 1024). Two safeguarded accelerations make it converge in ~10-25 sweeps, and neither
can raise the objective, because each only proposes a point and the proposal is kept only if it beats the plain
block step it replaces:

* subspace Gauss-Newton (:class:`_SubspaceGN`, ``gn_rank`` = k, default 128; 0 disables): before the rho-step,
  a variable-projection Gauss-Newton step for x restricted to the top-k eigenvectors of the first x-step's Gram
  matrix (with each target's active texels held at 0), followed by the exact rho-step at the new x; kept if it beats
  the exact rho-step at the old x (backtracking 1, 1/2, 1/4). Costs L(L+1)/2 weighted k x k Gram matrices of
  ``A' V`` per channel, a few percent of one N x N Gram;
* Anderson acceleration (type II, depth 5) of the albedo sequence: the extrapolated albedo is tried with its
  exact x-step and kept if its objective is below that after the plain rho and scale steps (an extra x-step
  when it is not).

The Gram matrices of the sweeps are formed from float32 products accumulated in float64 (``fast_gram``, ~2x
faster, entries to ~1e-7) when A' is float32; an x-step that would raise the objective is redone in float64. The
last x-step is exact without a float64 Gram matrix: :func:`objcam.solvers.jointqp.solve_nnls_pcg` solves it with
the exact float64 operator (two passes over A' per product) by conjugate gradients preconditioned with the last
sweep's float32 Gram matrices (formed at the final albedo), which converge in a few products; its KKT residual is
measured with the exact operator. (``xsolver="pcg"`` does every x-step that way, with a reference Gram refreshed
when the albedo has moved; memory-bound, it measured slower than forming the Gram matrices on a loaded 2-core
machine.)

Stopping rule: a sweep is {rho-step, subspace proposal, scale step, (Anderson-extrapolated) x-step,
majorise-minimise x-steps}; the solve stops when the relative decrease of the objective over one sweep is below
``tol`` (per channel with the quadratic prior; of the total with the edge prior, whose edges couple the channels)
or after ``max_iter`` sweeps.

Scale ambiguity. Without pixels of known albedo only the regularisers fix the global scale per channel (a c
with rho -> c rho, x -> x / c leaves the data unchanged). With lp = 0 the envmap priors prefer small x, so the
scale step pushes the largest albedo to the clip: ``max rho_c = 1`` (``JointResult.scale_at_clip``); with lp > 0
the two priors may balance inside the box. Either way the absolute albedo and radiance are not observable:
``JointResult.scale_ambiguous`` is True and estimates should be compared after a best-fit scale per channel
(:func:`evaluate_joint`; or globally with :func:`objcam.metrics.best_scale`). Pixels of known albedo
(``CameraBlock.fixed``: the object's, given in capture.toml) are held at their value in every step (the rho step
solves for the others, the Anderson candidate keeps them, the scale step scales only the others and counts the
fixed pixels' data, a quadratic in 1/c); they pin c, and ``scale_ambiguous`` is then False. Measured on the
bench's dots scene (the bunny's 586 pixels of known albedo): envmap SSIM 0.46 -> 0.51, absolute albedo error
19% -> 1.5%, 10 sweeps instead of 15 (16-20 s instead of 24).

The paper's variant (``method="paper"``): the same loop with the method's damped clipped steps instead of exact
block minimisation and no scale step: ``x <- max(0, x - alpha Q_c^{-1} (Q_c x - b))`` (Eq. 7, one step per
sweep) and ``rho <- clip(rho - beta H^{-1} (H rho - beta_rhs), rho_min, 1)``. It is not monotone (it stops
when the relative change of the objective is below ``tol``). If the objective becomes non-finite or exceeds
``diverge_factor`` x the best so far (e.g. ``alpha`` > 2 overshoots), the solve stops, returns the best
(last good) estimate seen and says so (``diverged``, ``message``). The same guard protects the exact variant
(which, being monotone, only trips on non-finite numbers).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse.linalg import splu

from objcam.envmap import EnvGrid
from objcam.metrics import relative_rmse
from objcam.solvers.basis import group_sizes
from objcam.solvers.jointqp import solve_nnls_pcg
from objcam.solvers.nnls import kkt_residual, solve_exact
from objcam.solvers.regularization import DEFAULT_LR_REL, DEFAULT_LS_REL, difference_operator
from objcam.solvers.search import golden_section
from objcam.threads import blas_threads, parallel_map, single_blas_thread

#: Default lower bound on the albedo (the model's (0, 1] made closed).
DEFAULT_RHO_MIN = 1e-3
#: Default initial albedo: mid-range, so that the first albedo step rarely clips at 1.
DEFAULT_RHO0 = 0.5

_BLOCK_BYTES = 64 * 2**20
#: Largest A' of which float64 and transposed float32 copies are kept (bigger ones are converted block by block).
_COPY_BYTES = 2 * 2**30

#: Envmap priors: quadratic smoothness, or the edge-preserving Huber prior (objcam.solvers.edges' model).
PRIORS = ("smooth", "edges")


class NoValidPixelsError(ValueError):
    """The joint solve was given no valid pixel at all (M = 0 in every camera)."""


# ------------------------------------------------------------------------------------------------ input handling


@dataclass
class CameraBlock:
    """One camera's data for :func:`solve_joint`.

    A: (M, N) float32/64 rho-free light transport (valid pixels x kept texels), not copied.
    Y: (M, L, C) pixel values per target (illumination) and channel; (M, L) means C = 1, (M,) means L = C = 1.
    pixel_index: (M,) flat indices ``r * W + c`` of the valid pixels on ``image_shape`` (needed when lp > 0).
    image_shape: (H, W) of the camera's image.
    rho0: initial albedo, (M, C), (M,) or a scalar; default :data:`DEFAULT_RHO0`.
    fixed: (M,) bool, pixels whose albedo is known: held at rho0 (clipped into [rho_min, 1]), not estimated. Any
        fixed pixel pins the scale that c rho, x / c otherwise leaves free.
    """

    A: np.ndarray
    Y: np.ndarray
    pixel_index: np.ndarray | None = None
    image_shape: tuple[int, int] | None = None
    rho0: np.ndarray | float | None = None
    fixed: np.ndarray | None = None


def _as_block(b: CameraBlock | Sequence) -> CameraBlock:
    if isinstance(b, CameraBlock):
        return b
    return CameraBlock(*b)


def _y3(Y: np.ndarray) -> np.ndarray:
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


# ------------------------------------------------------------------------------------- blocked dense kernels


def _rows_per_block(n: int) -> int:
    return max(1, _BLOCK_BYTES // (8 * max(n, 1)))


def _matmul(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``A @ X`` in float64 for A (M, N) float32/64 and X (N, k), converting A in row blocks."""
    m, n = A.shape
    out = np.empty((m, X.shape[1]))
    if A.dtype == np.float64:
        return np.matmul(A, X, out=out)
    step = _rows_per_block(n)
    for r0 in range(0, m, step):
        out[r0 : r0 + step] = np.asarray(A[r0 : r0 + step], dtype=np.float64) @ X
    return out


def _tmatmul(A: np.ndarray, U: np.ndarray) -> np.ndarray:
    """``A^T @ U`` in float64 for A (M, N) and U (M, k), converting A in row blocks."""
    m, n = A.shape
    if A.dtype == np.float64:
        return A.T @ U
    out = np.zeros((n, U.shape[1]))
    step = _rows_per_block(n)
    for r0 in range(0, m, step):
        out += np.asarray(A[r0 : r0 + step], dtype=np.float64).T @ U[r0 : r0 + step]
    return out


def weighted_gram(As: Sequence[np.ndarray], ws: Sequence[np.ndarray], n: int, fast: bool = False) -> np.ndarray:
    """``sum_p A_p^T diag(w_p) A_p`` (N, N) float64, exactly symmetric; w_p >= 0 (M_p,).

    ``fast=False``: float64 products over row blocks of ~64 MB. ``fast=True`` (float32 A only): each block of
    2048 rows is scaled and multiplied in float32 (sgemm, ~2x faster) and the block products are accumulated in
    float64; the relative error of the entries is ~1e-7 (float32 rounding over 2048-term sums).
    """
    G = np.zeros((n, n))
    for A, w in zip(As, ws):
        sw = np.sqrt(w)
        if fast and A.dtype == np.float32:
            sw32 = sw.astype(np.float32)
            with blas_threads():  # a large product: two threads are 1.6x faster here (objcam.threads)
                for r0 in range(0, A.shape[0], 2048):
                    blk = A[r0 : r0 + 2048] * sw32[r0 : r0 + 2048, None]
                    G += blk.T @ blk
        else:
            step = _rows_per_block(n)
            for r0 in range(0, A.shape[0], step):
                blk = np.asarray(A[r0 : r0 + step], dtype=np.float64) * sw[r0 : r0 + step, None]
                G += blk.T @ blk
    return 0.5 * (G + G.T)


def _col_sq_norms(A: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """``diag(A^T diag(w) A)`` (N,) float64."""
    m, n = A.shape
    out = np.zeros(n)
    step = _rows_per_block(n)
    for r0 in range(0, m, step):
        blk = np.asarray(A[r0 : r0 + step], dtype=np.float64)
        sq = blk * blk
        out += sq.sum(axis=0) if w is None else w[r0 : r0 + step] @ sq
    return out


# ---------------------------------------------------------------------------------- sparse box-constrained QP


@dataclass
class BoxQPResult:
    """x (n,), pivoting rounds, relative KKT residual (:func:`box_kkt_residual`), converged, LU factorisations."""

    x: np.ndarray
    iterations: int
    kkt_residual: float
    converged: bool
    factorizations: int


def box_kkt_residual(H: sp.spmatrix | np.ndarray, b: np.ndarray, x: np.ndarray, lo, hi) -> float:
    """Relative KKT residual of ``min 0.5 x^T H x - b^T x, lo <= x <= hi``.

    ``max_i H_ii |x_i - clip(x_i - g_i / H_ii, lo_i, hi_i)| / max(max_i |b_i|, tiny)`` with ``g = H x - b``
    (the projected-gradient natural residual scaled into units of b); 0 exactly at the minimiser. A variable with
    ``H_ii = 0`` is scaled by 1 instead (its residual is then ``|x_i - clip(x_i - g_i, lo_i, hi_i)|``).
    """
    x = np.asarray(x, dtype=np.float64)
    g = H @ x - b
    d = H.diagonal() if sp.issparse(H) else np.diag(H)
    lo = np.broadcast_to(lo, x.shape)
    hi = np.broadcast_to(hi, x.shape)
    dd = np.where(d > 0, d, 1.0)
    nat = dd * np.abs(x - np.clip(x - g / dd, lo, hi))
    scale = float(np.max(np.abs(b))) if b.size else 0.0
    return float(nat.max() / (scale if scale > 0 else 1.0)) if x.size else 0.0


def solve_box_qp(
    H: sp.spmatrix,
    b: np.ndarray,
    lo: float | np.ndarray,
    hi: float | np.ndarray,
    x0: np.ndarray | None = None,
    tol: float = 1e-12,
    max_iter: int | None = None,
) -> BoxQPResult:
    """Exact minimiser of ``0.5 x^T H x - b^T x`` subject to ``lo <= x <= hi`` for a sparse SPD ``H``.

    Block principal pivoting for box constraints: each variable is free, at its lower or at its upper bound;
    the free block ``H_FF x_F = b_F - H_FB x_B`` is solved by a sparse LU (SuperLU, minimum-degree ordering of
    H + H^T) with one step of iterative refinement; then every infeasible variable (a free one outside its box,
    a bounded one whose gradient points into the box) changes state at once while their number keeps falling
    (3 retries), otherwise only the last one (Murty's rule). Warm-started from the bound pattern of ``x0``. The
    returned x is clipped into the box and its true KKT residual (:func:`box_kkt_residual`) is reported. For the
    albedo step H is a diagonal plus a graph Laplacian (a Stieltjes matrix), the case this is meant for.
    """
    H = sp.csr_matrix(H, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    n = b.size
    lo = np.broadcast_to(np.asarray(lo, dtype=np.float64), (n,)).copy()
    hi = np.broadcast_to(np.asarray(hi, dtype=np.float64), (n,)).copy()
    if np.any(lo > hi):
        raise ValueError("lower bound above upper bound")
    if max_iter is None:
        max_iter = 10 * n + 100
    d = H.diagonal()
    if n == 0:
        return BoxQPResult(np.zeros(0), 0, 0.0, True, 0)
    # Purely diagonal H: closed form.
    if H.nnz == np.count_nonzero(d):
        x = np.clip(b / np.where(d > 0, d, 1.0), lo, hi)
        return BoxQPResult(x, 1, box_kkt_residual(H, b, x, lo, hi), True, 0)
    bscale = float(np.max(np.abs(b))) or 1.0
    tg = tol * bscale
    tx = tg / np.sqrt(d.max() * np.where(d > 0, d, d.max()))
    # state: 0 free, -1 at lo, +1 at hi
    if x0 is None:
        state = np.zeros(n, dtype=np.int8)
    else:
        x0 = np.asarray(x0, dtype=np.float64)
        state = np.where(x0 <= lo, -1, np.where(x0 >= hi, 1, 0)).astype(np.int8)
    x = np.empty(n)
    nfact = 0
    best_ninf, retries = n + 1, 3
    it = 0
    converged = False
    while True:
        free = state == 0
        x[state < 0] = lo[state < 0]
        x[state > 0] = hi[state > 0]
        F = np.flatnonzero(free)
        if F.size:
            Bd = np.flatnonzero(~free)
            HF = H[F]
            r = b[F] - HF[:, Bd] @ x[Bd] if Bd.size else b[F].copy()
            HFF = HF[:, F].tocsc()
            lu = splu(HFF, permc_spec="MMD_AT_PLUS_A")
            nfact += 1
            xf = lu.solve(r)
            xf = xf + lu.solve(r - HFF @ xf)
            x[F] = xf
        g = H @ x - b
        V = (free & ((x < lo - tx) | (x > hi + tx))) | ((state < 0) & (g < -tg)) | ((state > 0) & (g > tg))
        nv = int(V.sum())
        it += 1
        if nv == 0:
            converged = True
            break
        if it >= max_iter:
            break
        if nv < best_ninf:
            best_ninf, retries = nv, 3
            idx = np.flatnonzero(V)
        elif retries >= 1:
            retries -= 1
            idx = np.flatnonzero(V)
        else:
            idx = np.flatnonzero(V)[-1:]
        for i in idx:
            if state[i] == 0:
                state[i] = -1 if x[i] < lo[i] else 1
            else:
                state[i] = 0
    x = np.clip(x, lo, hi)
    return BoxQPResult(x, it, box_kkt_residual(H, b, x, lo, hi), converged, nfact)


# ------------------------------------------------------------------------------------------------ the problem


@dataclass
class JointResult:
    """Result of :func:`solve_joint`.

    x: (N, L, C) envmap radiance per kept texel, target and channel.
    rho: list over cameras of (M_p, C) albedo in [rho_min, 1].
    objective: (C,) final objective per channel (see the module docstring); ``objective.sum()`` is the total.
    history: (K+1,) total objective after the first x-step and after each sweep (non-increasing for "exact").
    history_channels: (K+1, C) the same per channel.
    step_history: total objective after every sub-step (x, rho, scale, x, ...), starting at (rho0, x = 0).
    iterations: sweeps done (the first x-step is sweep 0).
    converged: every channel met the relative-decrease tolerance within max_iter (and nothing diverged).
    diverged: the divergence guard tripped; x and rho are the best estimate seen (``message`` says which).
    message: one line on how the solve ended.
    kkt_x: (L, C) relative KKT residual of the final x for the final rho (x-subproblem, :func:`kkt_residual`).
    kkt_rho: (P, C) relative KKT residual of the final rho for the final x (rho-subproblem, box QP).
    scale_ambiguous: True unless some pixel is fixed: (c rho, x / c) fits the data equally; the regularisers pick c.
    scale_at_clip: (C,) whether max rho_c == 1, i.e. the clip fixed the scale of that channel.
    method: "exact" or "paper".  seconds: wall time.  info: weights and timings.
    """

    x: np.ndarray
    rho: list[np.ndarray]
    objective: np.ndarray
    history: np.ndarray
    history_channels: np.ndarray
    step_history: list[float]
    iterations: int
    converged: bool
    diverged: bool
    message: str
    kkt_x: np.ndarray
    kkt_rho: np.ndarray
    scale_ambiguous: bool
    scale_at_clip: np.ndarray
    method: str
    seconds: float
    info: dict[str, Any] = field(default_factory=dict)



class _Joint:
    """Prepared data and the per-channel kernels of the joint problem."""

    def __init__(self, blocks, grid, texel_index, ls, lr, lp, relative, rho_min, prior="smooth", edge_eps=0.05,
                 basis: sp.spmatrix | None = None):
        blocks = [_as_block(b) for b in blocks]
        if not blocks:
            raise NoValidPixelsError("joint solve: no camera blocks given -- nothing constrains the envmap")
        texel_index = np.asarray(texel_index, dtype=np.int64).ravel()
        self.n = n = texel_index.size
        self.As, self.Ys, self.Gs, self.rho0, self.fixed = [], [], [], [], []
        shape_lc = None
        for k, b in enumerate(blocks):
            A = np.asarray(b.A)
            if A.ndim != 2 or A.shape[1] != n:
                raise ValueError(f"camera {k}: A' is {A.shape}, expected (M, {n}) for {n} kept texels")
            Y = _y3(b.Y)
            if Y.shape[0] != A.shape[0]:
                raise ValueError(f"camera {k}: Y has {Y.shape[0]} rows, A' has {A.shape[0]}")
            if shape_lc is None:
                shape_lc = Y.shape[1:]
            elif Y.shape[1:] != shape_lc:
                raise ValueError(f"camera {k}: Y has (L, C) = {Y.shape[1:]}, camera 0 has {shape_lc}")
            if not (np.all(np.isfinite(Y)) and np.all(np.isfinite(A))):
                raise ValueError(f"camera {k}: A' and Y must be finite")
            self.As.append(A)
            self.Ys.append(Y)
            self.Gs.append(
                albedo_smoothness_operator(b.pixel_index, b.image_shape)
                if b.pixel_index is not None and b.image_shape is not None
                else None
            )
            self.rho0.append(b.rho0)
            fx = np.zeros(A.shape[0], bool) if b.fixed is None else np.asarray(b.fixed, bool).ravel()
            if fx.shape != (A.shape[0],):
                raise ValueError(f"camera {k}: fixed has {fx.size} entries, A' has {A.shape[0]} rows")
            if fx.any() and b.rho0 is None:
                raise ValueError(f"camera {k}: fixed pixels need their albedo in rho0")
            self.fixed.append(fx)
        self.L, self.C = shape_lc
        self.P = len(self.As)
        self.m_total = sum(A.shape[0] for A in self.As)
        if self.m_total == 0:
            raise NoValidPixelsError(
                "joint solve: no valid pixels (M = 0 in every camera) -- nothing constrains the albedo or the "
                "envmap; check the pixel masks (shadow region, saturation, object mask)"
            )
        if n == 0:
            raise ValueError("joint solve: no kept texels (N = 0)")
        if not 0.0 < rho_min < 1.0:
            raise ValueError("rho_min must be in (0, 1)")
        self.rho_min = float(rho_min)
        if min(ls, lr, lp) < 0:
            raise ValueError("regularisation weights must be >= 0")
        # Relative weight units.
        self.s_data = float(np.mean(sum(_col_sq_norms(A) for A in self.As)))
        self.t_data = float(
            sum(np.sum(Y * Y) for Y in self.Ys) / (self.m_total * self.C)
        )  # mean over pixels and channels of sum_l y^2
        if relative:
            self.ls, self.lr, self.lp = ls * self.s_data, lr * self.s_data, lp * self.t_data
        else:
            self.ls, self.lr, self.lp = float(ls), float(lr), float(lp)
        self.rel = dict(
            ls_rel=self.ls / self.s_data if self.s_data > 0 else float("nan"),
            lr_rel=self.lr / self.s_data if self.s_data > 0 else float("nan"),
            lp_rel=self.lp / self.t_data if self.t_data > 0 else float("nan"),
        )
        if self.lp > 0:
            for k, (A, G) in enumerate(zip(self.As, self.Gs)):
                if G is None and A.shape[0] > 1:
                    raise ValueError(f"camera {k}: lp > 0 needs pixel_index and image_shape for the albedo prior")
        self.basis = None if basis is None else sp.csr_matrix(basis)
        self.ridge_w = np.ones(n)
        if self.basis is not None:
            # x = P z: the solve runs on the merged columns A' P; the priors are those of the fine x
            if self.basis.shape[0] != n:
                raise ValueError(f"basis has {self.basis.shape[0]} rows, expected {n} kept texels")
            PT = self.basis.T.tocsr()
            self.As = [np.ascontiguousarray((PT @ A.T).T, dtype=A.dtype) for A in self.As]
            self.n = n = self.basis.shape[1]
            self.ridge_w = group_sizes(self.basis)
        self.Gs = [G if G is not None else sp.csr_matrix((0, A.shape[0])) for A, G in zip(self.As, self.Gs)]
        self.GtG = [(G.T @ G).tocsr() for G in self.Gs]
        # A' in float64 for the shading and right-hand sides (each a pass over A', memory-bound: converting float32
        # blocks on every pass cost ~3x), and transposed (N, M) float32 for the subspace Gauss-Newton's column
        # gathers (rows of A'^T are contiguous), made on first use; within _COPY_BYTES only
        self.A64 = [np.ascontiguousarray(A, dtype=np.float64) if A.dtype != np.float64 and A.size * 8 <= _COPY_BYTES
                    else (A if A.dtype == np.float64 else None) for A in self.As]
        self._AT32: list | None = None
        self._Asq: list | None = None
        self.D = difference_operator(grid, texel_index)
        if self.basis is not None:
            self.D = sp.csr_matrix(self.D @ self.basis)
        if prior not in PRIORS:
            raise ValueError(f"prior must be one of {PRIORS}, got {prior!r}")
        if not edge_eps > 0:
            raise ValueError("edge_eps must be > 0")
        self.prior = prior
        self.edge_eps_rel = float(edge_eps)
        # the quadratic (majorising) envmap prior in use: per target l, ls ||diag(sqrt(W_l)) D x||^2 + lr ||x||^2;
        # W = 1 for the smooth prior, the Huber majoriser's weights at the current point for the edge prior
        self.W = np.ones((self.L, self.D.shape[0]))
        self.edge_s = np.zeros(self.L)  # Huber scale s_l (fixed once set) and threshold eps_l = edge_eps s_l
        self.edge_thr = np.zeros(self.L)
        self.huber_on = False
        self._R_cache: dict[int, tuple[sp.csr_matrix, np.ndarray]] = {}
        self.t_gram = 0.0
        self.grams = 0
        self.fixed_vals = self.initial_rho()

    # -- initial values
    def initial_rho(self) -> list[np.ndarray]:
        out = []
        for A, r0 in zip(self.As, self.rho0):
            m = A.shape[0]
            r = np.full((m, self.C), DEFAULT_RHO0) if r0 is None else np.broadcast_to(
                np.asarray(r0, dtype=np.float64).reshape(-1, 1) if np.ndim(r0) == 1 else np.asarray(r0, float),
                (m, self.C),
            ).copy()
            out.append(np.clip(r, self.rho_min, 1.0))
        return out

    def pin(self, rho: list[np.ndarray]) -> list[np.ndarray]:
        """Hold the fixed pixels at their albedo (in place); returns rho."""
        for k, fx in enumerate(self.fixed):
            if fx.any():
                rho[k][fx] = self.fixed_vals[k][fx]
        return rho

    def bounds(self, k: int, c: int) -> tuple[np.ndarray | float, np.ndarray | float]:
        """(lo, hi) of camera k's albedo in channel c: [rho_min, 1], a fixed pixel's value for both."""
        fx = self.fixed[k]
        if not fx.any():
            return self.rho_min, 1.0
        v = self.fixed_vals[k][:, c]
        return np.where(fx, v, self.rho_min), np.where(fx, v, 1.0)

    @property
    def any_fixed(self) -> bool:
        return any(bool(fx.any()) for fx in self.fixed)

    # -- kernels
    def shading(self, X: np.ndarray) -> list[np.ndarray]:
        """S_p = A'_p x: list of (M_p, L, C)."""
        Xf = np.ascontiguousarray(X.reshape(self.n, -1))
        with blas_threads():  # a pass over A' (memory-bound): both cores' bandwidth
            return [(A64 @ Xf if A64 is not None else _matmul(A, Xf)).reshape(A.shape[0], self.L, self.C)
                    for A, A64 in zip(self.As, self.A64)]

    def weighted_col_sq(self, W: list[np.ndarray]) -> np.ndarray:
        """``sum_p (A'_p * A'_p)^T W_p`` (N, k) for weights W_p (M_p, k): the diagonals of the weighted Grams."""
        if self._Asq is None:
            self._Asq = [np.square(A, dtype=np.float32) if A.size * 4 <= _COPY_BYTES else None for A in self.As]
        out = np.zeros((self.n, W[0].shape[1] if W else 0))
        for A, Asq, w in zip(self.As, self._Asq, W):
            if A.shape[0] == 0:
                continue
            if Asq is not None:
                out += (Asq.T @ w.astype(np.float32)).astype(np.float64)
            else:
                for j in range(w.shape[1]):
                    out[:, j] += _col_sq_norms(A, w[:, j])
        return out

    def cols_t32(self, p: int, idx: np.ndarray) -> np.ndarray:
        """``A'_p[:, idx]^T`` (|idx|, M_p) float32 from the transposed copy (contiguous rows)."""
        if self._AT32 is None:
            self._AT32 = [np.ascontiguousarray(A.T, dtype=np.float32) if A.size * 4 <= _COPY_BYTES else None
                          for A in self.As]
        AT = self._AT32[p]
        return AT[idx] if AT is not None else np.asarray(self.As[p][:, idx].T, dtype=np.float32)

    def rhs(self, rho: list[np.ndarray], chans) -> np.ndarray:
        """b (N, L, C) = sum_p A'_p^T (rho_p * Y_p) (only ``chans`` filled)."""
        B = np.zeros((self.n, self.L, self.C))
        ch = np.asarray(chans)
        for A, A64, Y, r in zip(self.As, self.A64, self.Ys, rho):
            if A.shape[0] == 0:
                continue
            U = (r[:, None, ch] * Y[:, :, ch]).reshape(A.shape[0], -1)
            with blas_threads():
                B[:, :, ch] += (A64.T @ U if A64 is not None else _tmatmul(A, U)).reshape(self.n, self.L, ch.size)
        return B

    def gram(self, rho: list[np.ndarray], c: int, cache: dict, fast: bool = False) -> np.ndarray:
        """The data Gram matrix ``sum_p A'_p^T diag(rho_pc^2) A'_p`` (N, N) (no prior), cached by rho's values."""
        key = bytes([fast]) + b"".join(np.ascontiguousarray(r[:, c]).tobytes() for r in rho)
        if key in cache:
            return cache[key]
        t0 = time.perf_counter()
        Q = weighted_gram(self.As, [r[:, c] ** 2 for r in rho], self.n, fast=fast)
        self.t_gram += time.perf_counter() - t0
        self.grams += 1
        cache[key] = Q
        return Q

    # -- the envmap prior
    def R(self, l: int) -> sp.csr_matrix:
        """Target l's quadratic prior matrix ``ls D^T diag(W_l) D + lr I`` (sparse; the majoriser for edges)."""
        return self._R(l)[0]

    def R_dense(self, l: int) -> np.ndarray:
        return self._R(l)[1]

    def _R(self, l: int):
        key = hash(self.W[l].tobytes())
        hit = self._R_cache.get(l)
        if hit is None or hit[0] != key:
            R = sp.csr_matrix(self.ls * (self.D.T @ sp.diags(self.W[l]) @ self.D) + self.lr * sp.diags(self.ridge_w))
            hit = (key, R, R.toarray())
            self._R_cache[l] = hit
        return hit[1], hit[2]

    def edge_norms(self, X: np.ndarray) -> np.ndarray:
        """(L, E) RMS over channels of the differences ``D x_lc`` of every target."""
        DX = (self.D @ X.reshape(self.n, -1)).reshape(-1, self.L, self.C)
        return np.sqrt(np.mean(DX * DX, axis=2)).T

    def start_huber(self, X: np.ndarray) -> None:
        """Fix the Huber scale s_l (RMS edge of the current x_l) and threshold; tangent weights at X."""
        if self.prior != "edges" or self.ls <= 0:
            return
        r = self.edge_norms(X)
        s = np.sqrt(np.mean(r * r, axis=1)) if r.shape[1] else np.zeros(self.L)
        # a flat envmap has no edge scale: borrow the largest of the others (or keep it quadratic if none)
        s = np.where(s > 0, s, s.max() if s.size else 0.0)
        if not np.all(s > 0):
            return
        self.edge_s, self.edge_thr = s, self.edge_eps_rel * s
        self.huber_on = True
        self.tangent(X)

    def tangent(self, X: np.ndarray) -> None:
        """Edge prior: move the quadratic majoriser's weights to X, ``W_le = s_l / max(r_le, eps_l)``."""
        if not self.huber_on:
            return
        r = self.edge_norms(X)
        self.W = self.edge_s[:, None] / np.maximum(r, self.edge_thr[:, None])

    def prior_value(self, X: np.ndarray) -> float:
        """The envmap prior of the objective (total over targets and channels).

        smooth: ``sum_lc ls ||D x_lc||^2 + lr ||x_lc||^2``; edges: ``sum_l ls s_l 2 C sum_e huber_eps_l(r_le)
        + lr ||X||^2`` with r_le the RMS over channels of (D x_lc)_e."""
        if not self.huber_on:
            Xf = X.reshape(self.n, -1)
            DX = self.D @ Xf
            return float(self.ls * np.sum(DX * DX) + self.lr * np.sum(self.ridge_w[:, None] * Xf * Xf))
        r = self.edge_norms(X)
        h = np.where(r <= self.edge_thr[:, None], r * r / (2 * self.edge_thr[:, None]),
                     r - self.edge_thr[:, None] / 2)
        return float(self.ls * 2 * self.C * np.sum(self.edge_s * h.sum(axis=1))
                     + self.lr * np.einsum("n,nlc,nlc->", self.ridge_w, X, X))

    def reg_x(self, X: np.ndarray) -> np.ndarray:
        """(C,) the quadratic prior in use: sum_l ls ||diag(sqrt(W_l)) D x_lc||^2 + lr ||x_lc||^2 (for the edge
        prior the majoriser at the current tangent point, up to a constant)."""
        DX = (self.D @ X.reshape(self.n, -1)).reshape(-1, self.L, self.C)
        v = self.ls * np.einsum("le,elc->c", self.W, DX * DX)
        return v + self.lr * np.einsum("n,nlc,nlc->c", self.ridge_w, X, X)

    def reg_rho(self, rho: list[np.ndarray]) -> np.ndarray:
        """(C,) lp sum_p ||G_p rho_pc||^2."""
        out = np.zeros(self.C)
        if self.lp > 0:
            for G, r in zip(self.Gs, rho):
                Gr = G @ r
                out += self.lp * np.sum(Gr * Gr, axis=0)
        return out

    def data(self, rho, S) -> np.ndarray:
        out = np.zeros(self.C)
        for r, s, Y in zip(rho, S, self.Ys):
            res = r[:, None, :] * s - Y
            out += np.einsum("mlc,mlc->c", res, res)
        return out

    def objective(self, rho, X, S) -> np.ndarray:
        """(C,) per channel with the quadratic prior in use (the majoriser at the tangent point for edges): what
        the per-channel decisions of a sweep compare."""
        return self.data(rho, S) + self.reg_x(X) + self.reg_rho(rho)

    def true_objective(self, rho, X, S) -> np.ndarray:
        """(C,) the objective F: data and albedo prior per channel; the envmap prior, which the edge prior shares
        between the channels, split equally (so the sum is F)."""
        if not self.huber_on:
            return self.objective(rho, X, S)
        ridge = self.lr * np.einsum("n,nlc,nlc->c", self.ridge_w, X, X)
        return (self.data(rho, S) + self.reg_rho(rho) + ridge
                + (self.prior_value(X) - float(ridge.sum())) / self.C)

    def rho_system(self, rho_p, S_p, Y_p, k, c, prox=True):
        """(H, rhs) of camera k, channel c: H = diag(a) + lp G^T G, minimise 0.5 r^T H r - rhs^T r."""
        a, beta = _albedo_normal(S_p[:, :, c], Y_p[:, :, c], rho_p[:, c] if prox else None)
        H = sp.diags(a) + self.lp * self.GtG[k] if self.lp > 0 else sp.diags(a)
        return sp.csr_matrix(H), beta

    def rho_kkt(self, rho, S) -> np.ndarray:
        out = np.zeros((self.P, self.C))
        for k, (r, s, Y) in enumerate(zip(rho, S, self.Ys)):
            for c in range(self.C):
                if r.shape[0]:
                    H, beta = self.rho_system(r, s, Y, k, c, prox=False)
                    out[k, c] = box_kkt_residual(H, beta, r[:, c], *self.bounds(k, c))
        return out


def _albedo_normal(s: np.ndarray, y: np.ndarray, rho_prev: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
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
    channel ``clip(beta / a, rho_min, 1)`` (:meth:`_Joint.rho_system`'s rule, a never-lit pixel kept at
    ``rho_prev``), pixels ``fixed`` held at ``rho_prev``.

    A: (M, N) A' (float32 is converted in row blocks); Y: (M, L, C) photos; X: (N, L, C); rho_prev: (M, C).
    Returns (M, C)."""
    S = _matmul(A, X.reshape(X.shape[0], -1)).reshape(Y.shape)
    rho = np.empty(rho_prev.shape)
    for c in range(Y.shape[2]):
        a, beta = _albedo_normal(S[:, :, c], Y[:, :, c], rho_prev[:, c])
        rho[:, c] = np.clip(beta / a, rho_min, 1.0)
    if fixed is not None:
        rho[fixed] = rho_prev[fixed]
    return rho


def _chol(Q: np.ndarray):
    """cho_factor with a growing diagonal jitter if Q is not numerically positive definite."""
    try:
        return cho_factor(Q, lower=False, check_finite=False), 0.0
    except np.linalg.LinAlgError:
        dmax = float(np.max(np.abs(np.diag(Q)))) or 1.0
        rel = 1e-12
        while True:
            try:
                j = rel * dmax
                return cho_factor(Q + j * np.eye(Q.shape[0]), lower=False, check_finite=False), j
            except np.linalg.LinAlgError:
                rel *= 100.0
                if rel > 1e2:
                    raise


class _SubspaceGN:
    """Gauss-Newton proposals for x in the span of the top ``k`` eigenvectors V of ``sum_p A'_p^T A'_p``.

    With the albedo eliminated pixel by pixel (variable projection: for fixed x the best rho_i is a per-pixel
    1-D least squares), the Gauss-Newton model of the objective in ``dx_l = V_l dz_l`` is

        sum_i || P_i (r_i + rho_i [b_il . dz_l]_l) ||^2 + sum_l (x_l + V_l dz_l)^T R (x_l + V_l dz_l),

    ``r_i`` (L,) the pixel's residuals, ``V_l`` the basis V with the rows of target l's active texels (x = 0)
    zeroed (they stay at 0 to first order), ``b_il = V_l^T a_i`` the pixel's transport row in that basis and
    ``P_i`` the projection orthogonal to its shading vector ``s_i`` (L,) (the identity for a pixel whose albedo
    sits at a bound). Its normal matrix (k L x k L) needs L (L+1) / 2 weighted k x k Gram matrices of
    ``B_l = A' V_l`` (M k^2 flops each, in float32: a proposal needs no more), and ``B_l`` is kept per target and
    channel and updated only by the texels that changed state. The proposal moves x along the directions the
    data sees best -- those in which x can compensate an albedo change: the slow valley of the alternation.
    """

    def __init__(self, J: "_Joint", k: int, fast: bool, K: np.ndarray | None = None):
        self.J = J
        n = J.n
        self.k = k = int(min(k, n))
        if K is None:
            K = weighted_gram(J.As, [np.ones(A.shape[0]) for A in J.As], n, fast=fast)
        evals, evecs = np.linalg.eigh(K)
        self.V = np.ascontiguousarray(evecs[:, ::-1][:, :k])
        self.V32 = self.V.astype(np.float32)
        self.B = [(A64 @ self.V if A64 is not None else _matmul(A, self.V)).astype(np.float32)
                  for A, A64 in zip(J.As, J.A64)]
        self.cache: dict[tuple[int, int], tuple[np.ndarray, list[np.ndarray]]] = {}

    def _cols(self, p: int, idx: np.ndarray) -> np.ndarray:
        """``A'_p[:, idx] @ V[idx]`` in float32 (M, k)."""
        return self.J.cols_t32(p, idx).T @ self.V32[idx]

    def _basis(self, l: int, c: int, active: np.ndarray) -> list[np.ndarray]:
        """``A'_p V_l`` per camera for target l, channel c (cached; updated by the texels that changed state)."""
        J = self.J
        old = self.cache.get((l, c))
        if old is not None:
            oa, Bs = old
            on = np.flatnonzero(active & ~oa)  # became active: remove
            off = np.flatnonzero(~active & oa)  # became free: add
            if on.size + off.size <= J.n // 4:
                for p, A in enumerate(J.As):
                    if on.size:
                        Bs[p] -= self._cols(p, on)
                    if off.size:
                        Bs[p] += self._cols(p, off)
                self.cache[(l, c)] = (active.copy(), Bs)
                return Bs
        za = np.flatnonzero(active)
        zf = np.flatnonzero(~active)
        Bs = []
        for p, A in enumerate(J.As):
            if za.size == 0:
                Bs.append(self.B[p].copy())
            elif za.size <= zf.size:
                Bs.append(self.B[p] - self._cols(p, za))
            else:
                Bs.append(self._cols(p, zf) if zf.size else np.zeros_like(self.B[p]))
        self.cache[(l, c)] = (active.copy(), Bs)
        return Bs

    def _coupled(self, p, r, s, res, a, Bl, H, g) -> None:
        """lp > 0: eliminate the albedo of camera p through its sparse block ``diag(a) + lp G^T G`` (SuperLU)."""
        J, k, L = self.J, self.k, self.J.L
        r2 = r * r
        for l in range(L):
            g[l * k:(l + 1) * k] += Bl[l][p].T.astype(np.float64) @ (r * res[:, l])
            blk = ((Bl[l][p] * r2.astype(np.float32)[:, None]).T @ Bl[l][p]).astype(np.float64)
            H[l * k:(l + 1) * k, l * k:(l + 1) * k] += blk
        free = np.flatnonzero((r > J.rho_min) & (r < 1.0) & ~J.fixed[p])
        if free.size == 0:
            return
        Hrr = (sp.diags(a) + J.lp * J.GtG[p]).tocsr()[free][:, free].tocsc()
        Hrr = Hrr + sp.identity(free.size, format="csc") * (1e-12 * float(Hrr.diagonal().max() or 1.0))
        grad_r = (np.einsum("ml,ml->m", s, res) + J.lp * (J.GtG[p] @ r))[free]
        Cz = np.concatenate([(s[free, l] * r[free])[:, None] * Bl[l][p][free].astype(np.float64)
                             for l in range(L)], axis=1)
        lu = splu(Hrr, permc_spec="MMD_AT_PLUS_A")
        Yc = lu.solve(Cz)
        H -= Cz.T @ Yc
        g -= Cz.T @ lu.solve(grad_r)

    def direction(self, rho, X, S, chans) -> np.ndarray:
        """(N, L, C) the proposal's step for the channels ``chans`` (zero elsewhere); the channels are
        independent problems, solved on a thread per core (their products release the GIL)."""
        # what the threads share is made once before them: the transposed copy of A', each target's prior matrix
        self.J.cols_t32(0, np.zeros(0, dtype=np.int64))
        for l in range(self.J.L):
            self.J.R(l)
        dX = np.zeros_like(X)
        for c, d in zip(chans, parallel_map(lambda c: self._channel(rho, X, S, int(c)), list(chans))):
            if d is not None:
                dX[:, :, c] = d
        return dX

    def _channel(self, rho, X, S, c: int) -> np.ndarray | None:
        J, k, L = self.J, self.k, self.J.L
        H = np.zeros((L * k, L * k))
        g = np.zeros(L * k)
        act = [X[:, l, c] <= 0 for l in range(L)]
        Vl = [np.where(act[l][:, None], 0.0, self.V) for l in range(L)]
        Bl = [self._basis(l, c, act[l]) for l in range(L)]
        for l in range(L):
            RVl = J.R(l) @ Vl[l]
            H[l * k:(l + 1) * k, l * k:(l + 1) * k] += Vl[l].T @ RVl
            g[l * k:(l + 1) * k] += RVl.T @ X[:, l, c]
        for p in range(J.P):
            r = rho[p][:, c]
            if r.size == 0:
                continue
            s = S[p][:, :, c]
            res = r[:, None] * s - J.Ys[p][:, :, c]
            a = np.einsum("ml,ml->m", s, s)
            r2 = r * r
            if J.lp > 0:
                self._coupled(p, r, s, res, a, Bl, H, g)
                continue
            free = (a > 1e-12 * (a.max() if a.size else 1.0)) & (r > J.rho_min) & (r < 1.0) & ~J.fixed[p]
            inv_a = np.where(free, 1.0 / np.where(free, a, 1.0), 0.0)
            # P r = r - s (s.r)/a
            pres = res - s * (np.einsum("ml,ml->m", s, res) * inv_a)[:, None]
            for l in range(L):
                g[l * k:(l + 1) * k] += Bl[l][p].T.astype(np.float64) @ (r * pres[:, l])
                for l2 in range(l, L):
                    w = (r2 * ((1.0 if l == l2 else 0.0) - s[:, l] * s[:, l2] * inv_a)).astype(np.float32)
                    blk = ((Bl[l][p] * w[:, None]).T @ Bl[l2][p]).astype(np.float64)
                    H[l * k:(l + 1) * k, l2 * k:(l2 + 1) * k] += blk
                    if l2 != l:
                        H[l2 * k:(l2 + 1) * k, l * k:(l + 1) * k] += blk.T
        H = 0.5 * (H + H.T)
        try:
            fac, _ = _chol(H)
            dz = -cho_solve(fac, g, check_finite=False)
        except np.linalg.LinAlgError:
            return None
        return np.stack([Vl[l] @ dz[l * k:(l + 1) * k] for l in range(L)], axis=1)


class _Anderson:
    """Type-II Anderson acceleration of a fixed-point map z -> g(z), one history per channel."""

    def __init__(self, depth: int):
        self.depth = depth
        self.z: list[np.ndarray] = []
        self.g: list[np.ndarray] = []

    def reset(self) -> None:
        self.z.clear()
        self.g.clear()

    def step(self, z: np.ndarray, g: np.ndarray) -> np.ndarray | None:
        """Record (z, g(z)); return the extrapolated point, or None while the history is too short."""
        self.z.append(z.copy())
        self.g.append(g.copy())
        if len(self.z) > self.depth + 1:
            self.z.pop(0)
            self.g.pop(0)
        if len(self.z) < 2:
            return None
        F = np.stack([gg - zz for zz, gg in zip(self.z, self.g)], axis=1)
        Gm = np.stack(self.g, axis=1)
        dF = np.diff(F, axis=1)
        dG = np.diff(Gm, axis=1)
        # min ||f_k - dF gamma||, lightly regularised for near-collinear histories.
        M = dF.T @ dF
        reg = 1e-10 * (np.trace(M) or 1.0)
        try:
            gamma = np.linalg.solve(M + reg * np.eye(M.shape[0]), dF.T @ F[:, -1])
        except np.linalg.LinAlgError:
            return None
        return Gm[:, -1] - dG @ gamma


def solve_joint(
    blocks: Sequence[CameraBlock | tuple],
    grid: EnvGrid,
    texel_index: np.ndarray,
    ls: float = DEFAULT_LS_REL,
    lr: float = DEFAULT_LR_REL,
    lp: float = 0.0,
    method: str = "exact",
    relative: bool = True,
    tol: float = 1e-6,
    max_iter: int = 100,
    rho_min: float = DEFAULT_RHO_MIN,
    scale_step: bool = True,
    accelerate: bool = True,
    anderson_depth: int = 5,
    fast_gram: bool = True,
    gn_rank: int = 128,
    gn_inner: int = 1,
    alpha: float = 0.5,
    beta: float = 0.5,
    diverge_factor: float = 10.0,
    qp_tol: float = 1e-10,
    prior: str = "smooth",
    edge_eps: float = 0.05,
    edge_steps: int = 2,
    rho_init: Sequence[np.ndarray] | None = None,
    xsolver: str = "gram",
    cg_refresh: int = 12,
    polish: bool = True,
    basis: sp.spmatrix | None = None,
) -> JointResult:
    """Jointly recover the albedo of every camera and the L envmaps (per colour channel); see the module docstring.

    blocks: one :class:`CameraBlock` (or tuple ``(A', Y[, pixel_index, image_shape, rho0])``) per camera; all
        share the N kept texels ``texel_index`` on ``grid`` and the (L, C) layout of Y.
    ls, lr: envmap smoothness and ridge weights, relative to ``mean(diag(sum_p A'_p^T A'_p))``;
    lp: albedo smoothness weight, relative to ``mean_{pixels, channels} sum_l y^2``; ``relative=False`` takes
        all three as absolute.
    prior: "smooth" (quadratic ``ls ||D x||^2``) or "edges" (the edge-preserving Huber prior, minimised by
        majorise-minimise inside the alternation; ``edge_eps`` its threshold relative to the RMS edge,
        ``edge_steps`` the majorise-minimise x-steps per sweep, all on the sweep's Gram matrices); see the
        module docstring.
    method: "exact" (exact block-coordinate descent, monotone) or "paper" (damped clipped steps, ``alpha`` for x,
        ``beta`` for rho; no scale step, no acceleration).
    tol: stop when the relative decrease of the objective over one sweep is below ``tol`` (smooth prior: per
        channel; edges: of the total, which the shared edges couple); max_iter sweeps.
    rho_min: lower clip of the albedo (upper is 1).  scale_step: the exact 1-D scale minimisation (exact only).
    accelerate, anderson_depth: safeguarded Anderson acceleration of the albedo sequence (exact only; see the
        module docstring); the objective stays non-increasing.
    gn_rank: rank k of the subspace Gauss-Newton proposals (0 disables; see the module docstring);
        gn_inner: proposals per sweep before the x-step (1 is as good as more on the test scenes).
    fast_gram: form the Gram matrices of the sweeps from float32 products (float64 accumulation, ~2x faster,
        entries to ~1e-7) when A' is float32; a sweep whose x-step would raise the objective is redone in float64,
        and the final x-step is always float64, so the returned x is exact for the returned rho.
    diverge_factor: the divergence guard (see the module docstring).
    qp_tol: tolerance of the exact x- and rho-subproblem solves.
    rho_init: optional initial albedo per camera (list of (M_p, C)), overriding the blocks' rho0.
    xsolver: how the sweeps' exact x-steps solve their QP: "gram" (default: form the sweep's Gram matrices,
        float32 products with ``fast_gram``; solve exactly by :func:`objcam.solvers.nnls.solve_exact`) or "pcg"
        (:mod:`objcam.solvers.jointqp`: Q applied by passes over A', a reference Gram matrix per channel as the
        preconditioner, refreshed when a step needs more than ``cg_refresh`` operator applications per pivoting
        round; memory-bound, it measured slower than "gram" on a loaded 2-core machine). Either way the final
        x-step is polished by PCG against the exact float64 operator (:mod:`objcam.solvers.jointqp`) with the last
        sweep's float32 Gram matrices as the preconditioner, so the returned x is exact (KKT ~ qp_tol) for the
        returned rho without forming float64 Gram matrices. The paper's method always forms them.
    polish: do that final exact x-step (default). ``False`` skips it for a solve whose result is only a starting
        point (the solve stage's first solve before a bounce refit): x is then the last sweep's x-step on float32
        Gram matrices (``kkt_x`` says how exact).
    basis: optional (N, N') 0/1 matrix P of texel groups (:func:`objcam.solvers.basis.texel_basis`): the solve
        runs on z with x = P z (A' P, the priors of the fine x: ``D P`` and the ridge ``||P z||^2``; the weights
        stay relative to the fine A'), and returns x = P z; ``kkt_x`` is the merged problem's.

    Raises :class:`NoValidPixelsError` (a ValueError) when no camera has a valid pixel. Runs with one BLAS thread.
    """
    if method not in ("exact", "paper"):
        raise ValueError(f"method must be 'exact' or 'paper', got {method!r}")
    if method == "paper" and not (alpha > 0 and beta > 0):
        raise ValueError("alpha and beta must be > 0")
    if edge_steps < 1:
        raise ValueError("edge_steps must be >= 1")
    if xsolver not in ("pcg", "gram"):
        raise ValueError(f"xsolver must be 'pcg' or 'gram', got {xsolver!r}")
    t_start = time.perf_counter()
    J = _Joint(blocks, grid, texel_index, ls, lr, lp, relative, rho_min, prior=prior, edge_eps=edge_eps,
               basis=basis)
    n, L, C, P = J.n, J.L, J.C, J.P
    exact = method == "exact"
    accelerate = accelerate and exact
    timers = dict(x=0.0, rho=0.0, gn=0.0, scale=0.0)
    use_pcg = exact and xsolver == "pcg"
    ref: dict = dict(G={}, stale=set(), applications=0, rounds=0, refreshes=0, steps=0)
    sizes = [A.shape[0] for A in J.As]
    splits = np.cumsum(sizes)[:-1]
    fixed_flat = np.concatenate(J.fixed)  # the pixels of known albedo, in the order of flat()
    # the Gram matrices of the current sweep, keyed by the albedo values (shared by the x-steps of one sweep)
    gram_cache: dict = {}

    def flat(rho, c):
        return np.concatenate([r[:, c] for r in rho])

    def unflat(z, rho, c):
        for r, part in zip(rho, np.split(z, splits)):
            r[:, c] = part

    def x_step_pcg(rho, X, chans, warm, grams=None):
        """The exact x-step by :func:`objcam.solvers.jointqp.solve_nnls_pcg`: Q applied by passes over A', the
        preconditioner from ``grams`` {c: Gram} (e.g. this albedo's float32 Grams) or the reference Grams."""
        t0 = time.perf_counter()
        X = X.copy()
        kk = np.zeros((L, C))
        chans = [int(c) for c in chans]
        B = J.rhs(rho, chans)
        for c in chans:
            if grams is None and (c not in ref["G"] or c in ref["stale"]):
                ref["G"][c] = J.gram(rho, c, {}, fast=True)
                ref["stale"].discard(c)
                ref["refreshes"] += 1
        Gs = grams if grams is not None else ref["G"]
        cols = [(l, c) for c in chans for l in range(L)]
        per_target = J.huber_on
        pkeys: dict[tuple[int, int], int] = {}
        precond, group = [], np.zeros(len(cols), dtype=np.int64)
        for k, (l, c) in enumerate(cols):
            key = (c, l if per_target else 0)
            if key not in pkeys:
                pkeys[key] = len(precond)
                precond.append(Gs[c] + J.R_dense(key[1]))
            group[k] = pkeys[key]
        W = [np.stack([r[:, c] ** 2 for c in chans], axis=1) if r.shape[0] else np.zeros((0, len(chans)))
             for r in rho]  # (M_p, len(chans))
        cpos = {c: j for j, c in enumerate(chans)}
        dg = J.weighted_col_sq(W)  # (N, len(chans))
        diag_Q = np.stack([dg[:, cpos[c]] + J.R(l).diagonal() for l, c in cols], axis=1)
        col_l = np.array([l for l, _ in cols])
        col_cj = np.array([cpos[c] for _, c in cols])

        def apply_Q(V, which):
            with blas_threads():  # two passes over A'
                return _apply_Q(V, which)

        def _apply_Q(V, which):
            which = np.asarray(which)
            out = np.zeros_like(V)
            for A, A64, w in zip(J.As, J.A64, W):
                if A.shape[0] == 0:
                    continue
                U = A64 @ V if A64 is not None else _matmul(A, V)
                U *= w[:, col_cj[which]]
                out += A64.T @ U if A64 is not None else _tmatmul(A, U)
            for l in np.unique(col_l[which]):
                j = np.flatnonzero(col_l[which] == l)
                out[:, j] += J.R(int(l)) @ V[:, j]
            return out

        Bm = np.stack([B[:, l, c] for l, c in cols], axis=1)
        X0 = np.stack([X[:, l, c] for l, c in cols], axis=1) if warm else np.zeros((n, len(cols)))
        p0 = None if warm else np.ones((n, len(cols)), dtype=bool)
        res = solve_nnls_pcg(apply_Q, diag_Q, precond, group, Bm, X0, passive0=p0, tol=qp_tol)
        for k, (l, c) in enumerate(cols):
            X[:, l, c] = res.x[:, k]
            kk[l, c] = res.kkt_residual[k]
        ref["applications"] += res.cg_iterations
        ref["rounds"] += res.rounds
        ref["steps"] += 1
        if grams is None and res.cg_iterations > cg_refresh * res.rounds:
            ref["stale"].update(chans)  # the albedo moved away from the reference: new Gram at the next x-step
        timers["x"] += time.perf_counter() - t0
        return X, kk

    def x_step(rho, X, chans, warm, fast=fast_gram):
        """Exact (or damped) x for the given rho and the quadratic prior in use, on channels ``chans``; returns
        (X, kkt) for all channels. One Gram matrix per channel; with per-target prior weights (edges) one
        factorisation per (target, channel), else one per channel for all its targets."""
        if use_pcg:
            return x_step_pcg(rho, X, chans, warm)
        t0 = time.perf_counter()
        X = X.copy()
        kk = np.zeros((L, C))
        B = J.rhs(rho, chans)
        per_target = J.huber_on
        groups = [[l] for l in range(L)] if per_target else [list(range(L))]
        # the channels' Gram matrices first (each a large product on every core), then the independent QPs of
        # the (target group, channel) pairs on a thread per core, each with one BLAS thread
        grams = {int(c): J.gram(rho, c, gram_cache, fast=fast) for c in chans}
        for ls_ in groups:
            J.R_dense(ls_[0])  # built (and cached) here, not by two threads at once
        # the tasks read the warm start from X; it is written only after every task has returned

        def one(task):
            c, ls_ = task
            Q = grams[c] + J.R_dense(ls_[0])
            Bc = B[:, ls_, c]
            if exact:
                p0 = X[:, ls_, c] > 0 if warm else None
                res = solve_exact(Q, Bc, tol=qp_tol, passive0=p0)
                return res.x, res.kkt_residual
            fac, _ = _chol(Q)
            Xc = X[:, ls_, c]
            Xc = np.maximum(Xc - alpha * cho_solve(fac, Q @ Xc - Bc, check_finite=False), 0.0)
            return Xc, kkt_residual(Q, Bc, Xc)

        tasks = [(int(c), ls_) for c in chans for ls_ in groups]
        for (c, ls_), (xc, kc) in zip(tasks, parallel_map(one, tasks)):
            X[:, ls_, c] = xc
            kk[ls_, c] = kc
        timers["x"] += time.perf_counter() - t0
        return X, kk

    def rho_step(rho, S, chans):
        t0 = time.perf_counter()
        rho = [r.copy() for r in rho]
        for k in range(P):
            if rho[k].shape[0] == 0:
                continue
            for c in chans:
                H, bt = J.rho_system(rho[k], S[k], J.Ys[k], k, c)
                fx = J.fixed[k]
                if exact:
                    if J.lp > 0 and fx.any():
                        # the fixed pixels' terms move to the right-hand side of the free pixels' box QP
                        fr = ~fx
                        Hc = H.tocsr()
                        r = rho[k][:, c].copy()
                        bf = bt[fr] - Hc[fr][:, fx] @ r[fx]
                        r[fr] = solve_box_qp(Hc[fr][:, fr], bf, J.rho_min, 1.0, x0=r[fr], tol=qp_tol).x
                    elif J.lp > 0:
                        r = solve_box_qp(H, bt, J.rho_min, 1.0, x0=rho[k][:, c], tol=qp_tol).x
                    else:
                        r = np.clip(bt / H.diagonal(), *J.bounds(k, c))
                else:
                    if J.lp > 0:
                        step = splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A").solve(H @ rho[k][:, c] - bt)
                    else:
                        step = rho[k][:, c] - bt / H.diagonal()
                    r = np.clip(rho[k][:, c] - beta * step, *J.bounds(k, c))
                rho[k][:, c] = r
        timers["rho"] += time.perf_counter() - t0
        return rho

    def scale(rho, X, S, chans):
        """Minimise over c > 0 the objective F at (clip(c rho, rho_min, 1), x / c) per channel (in place).

        Between the clips the data term is constant; beyond them (c rho_i > 1 for a few pixels, which then stay
        at 1) the data of those pixels changes; the envmap prior is evaluated exactly (for the edge prior, the
        Huber of the shared edges with this channel scaled). The 1-D function is evaluated on a log grid around
        the unclipped range, refined by golden-section search, and the best c (c = 1 included) is taken; the
        objective is then recomputed directly and the step undone unless it decreased, so F never increases.
        With lp = 0 one evaluation costs O(log M): the pixels clipped at either bound are a prefix and a suffix
        of the albedo sorted once, and their data terms are quadratics in 1/c summed by prefix sums. Fixed pixels
        (known albedo) keep their albedo, so their data term is a quadratic in 1/c too: they pin c.
        """
        t0 = time.perf_counter()
        live = [k for k in range(P) if rho[k].shape[0]]
        for c in chans:
            free_k = [~J.fixed[k] for k in live]
            r_all = np.concatenate([rho[k][fr, c] for k, fr in zip(live, free_k)])
            if r_all.size == 0:
                continue
            rmax, rmin = float(r_all.max()), float(r_all.min())
            # the fixed pixels' data: sum (rho s / c - y)^2 = fa / c^2 - 2 fb / c + fy
            fa = fb = fy = 0.0
            for k, fr in zip(live, free_k):
                fx = ~fr
                if fx.any():
                    rs_, sh_, y_ = rho[k][fx, c][:, None], S[k][fx][:, :, c], J.Ys[k][fx][:, :, c]
                    fa += float(np.sum((rs_ * sh_) ** 2))
                    fb += float(np.sum(rs_ * sh_ * y_))
                    fy += float(np.sum(y_ * y_))
            if J.huber_on:
                DX = (J.D @ X[:, :, c])  # (E, L)
                others = (np.einsum("elc,elc->el", *(2 * [(J.D @ X.reshape(n, -1)).reshape(-1, L, C)]))
                          - DX * DX)
                xx_c = float(np.einsum("n,nl,nl->", J.ridge_w, X[:, :, c], X[:, :, c]))
                xx_o = float(np.einsum("n,nlc,nlc->", J.ridge_w, X, X)) - xx_c
                thr = J.edge_thr[None, :]

                def prior_at(cs):
                    r = np.sqrt(np.maximum(others + DX * DX / cs**2, 0.0) / C)
                    h = np.where(r <= thr, r * r / (2 * thr), r - thr / 2)
                    return float(J.ls * 2 * C * np.sum(J.edge_s * h.sum(axis=0)) + J.lr * (xx_o + xx_c / cs**2))
            else:
                rx = float(J.reg_x(X)[c])

                def prior_at(cs):
                    return rx / cs**2
            if prior_at(1.0) <= 0:
                continue
            if J.lp > 0:
                r_c = [rho[k][:, c] for k in live]
                s_c = [S[k][:, :, c] for k in live]
                y_c = [J.Ys[k][:, :, c] for k in live]
                g_c = [J.Gs[k] for k in live]
                f_c = [J.fixed[k] for k in live]

                def data_at(cs):
                    v = 0.0
                    for r, sh, y, G, fx in zip(r_c, s_c, y_c, g_c, f_c):
                        rr = np.where(fx, r, np.clip(r * cs, J.rho_min, 1.0))
                        res = rr[:, None] * (sh / cs) - y
                        v += float(np.sum(res * res))
                        gr = G @ rr
                        v += J.lp * float(gr @ gr)
                    return v
            else:
                sh = np.concatenate([S[k][fr][:, :, c] for k, fr in zip(live, free_k)])
                yv = np.concatenate([J.Ys[k][fr][:, :, c] for k, fr in zip(live, free_k)])
                order = np.argsort(r_all, kind="stable")
                rs = r_all[order]
                sh, yv = sh[order], yv[order]
                res = rs[:, None] * sh - yv
                cum = [np.concatenate([[0.0], np.cumsum(v)]) for v in (
                    np.einsum("ml,ml->m", res, res), np.einsum("ml,ml->m", sh, sh),
                    np.einsum("ml,ml->m", sh, yv), np.einsum("ml,ml->m", yv, yv))]
                e_tot = cum[0][-1]
                m_all = rs.size

                def data_at(cs):
                    lo = int(np.searchsorted(rs, J.rho_min / cs, side="left"))  # r cs < rho_min: prefix [0, lo)
                    hi = int(np.searchsorted(rs, 1.0 / cs, side="right"))  # r cs > 1: suffix [hi, M)
                    hi = max(hi, lo)
                    e, aa_, bb, yy = (cm[lo] - cm[0] for cm in cum)
                    v = e_tot - e + (J.rho_min**2 * aa_ / cs**2 - 2 * J.rho_min * bb / cs + yy)
                    e, aa_, bb, yy = (cm[m_all] - cm[hi] for cm in cum)
                    return float(v - e + (aa_ / cs**2 - 2 * bb / cs + yy) + (fa / cs**2 - 2 * fb / cs + fy))

            def f(t):
                cs = np.exp(t)
                return data_at(cs) + prior_at(cs)

            t_lo, t_hi = np.log(J.rho_min / rmin), np.log(1.0 / rmax)
            rr_c = J.reg_rho([rho[k] for k in live])[c]
            rx_c = float(J.reg_x(X)[c])
            t_free = t_hi if rr_c <= 0 else float(np.clip(0.25 * np.log(max(rx_c, 1e-300) / rr_c), t_lo, t_hi))
            ts = np.unique(np.concatenate([np.linspace(t_lo, t_hi + np.log(4.0), 24), [0.0, t_free, t_hi]]))
            vals = np.array([f(t) for t in ts])
            j = int(np.argmin(vals))
            a_, b_ = ts[max(j - 1, 0)], ts[min(j + 1, ts.size - 1)]
            best_t, best_v = ts[j], vals[j]
            t, v = golden_section(f, a_, b_, tol=1e-8, max_iter=40)
            if v < best_v:
                best_t, best_v = t, v
            if best_v >= f(0.0):
                continue
            cs = float(np.exp(best_t))
            before = float(J.true_objective(rho, X, S).sum())
            saved = ([rho[k][:, c].copy() for k in range(P)], [S[k][:, :, c].copy() for k in range(P)],
                     X[:, :, c].copy())
            for k in range(P):
                rho[k][:, c] = np.where(J.fixed[k], rho[k][:, c], np.clip(rho[k][:, c] * cs, J.rho_min, 1.0))
                S[k][:, :, c] /= cs
            X[:, :, c] /= cs
            if not float(J.true_objective(rho, X, S).sum()) < before:  # a rounding-level gain: undo
                for k in range(P):
                    rho[k][:, c], S[k][:, :, c] = saved[0][k], saved[1][k]
                X[:, :, c] = saved[2]
        timers["scale"] += time.perf_counter() - t0

    def total(rho, X, S) -> float:
        return float(J.true_objective(rho, X, S).sum())

    with single_blas_thread():
        rho = J.initial_rho() if rho_init is None else J.pin([
            np.clip(np.asarray(r, dtype=np.float64).reshape(A.shape[0], C), J.rho_min, 1.0).copy()
            for r, A in zip(rho_init, J.As)])
        X = np.zeros((n, L, C))
        S = [np.zeros((A.shape[0], L, C)) for A in J.As]
        step_hist = [total(rho, X, S)]
        per_channel = not (prior == "edges")  # the shared edges couple the channels: stop on the total
        active = np.ones(C, dtype=bool)
        aa = [_Anderson(anderson_depth) for _ in range(C)]
        stats = dict(accepted=0, rejected=0, float64_redo=0, gn_accepted=0, gn_rejected=0, mm_steps=0)
        # sweep 0: x for the initial albedo (quadratic prior); the edge prior takes its scale from this x
        X, kkt_x = x_step(rho, X, np.arange(C), warm=False)
        S = J.shading(X)
        if prior == "edges":
            J.start_huber(X)  # F is the Huber objective from here: the histories start at this point
            if J.huber_on:
                step_hist = []
        obj_t = J.true_objective(rho, X, S)
        step_hist.append(float(obj_t.sum()))
        hist = [obj_t.copy()]
        gn = None
        if exact and gn_rank and gn_rank > 0:
            # its basis: the top eigenvectors of the first sweep's Gram matrix (the data's strong directions)
            K0 = ref["G"].get(0) if use_pcg else J.gram(rho, 0, gram_cache, fast=fast_gram)  # cached
            gn = _SubspaceGN(J, gn_rank, fast_gram, K=K0)
        best = (float(obj_t.sum()), X.copy(), [r.copy() for r in rho], [s.copy() for s in S], obj_t.copy(),
                kkt_x.copy(), 0)
        diverged = False
        message = ""
        iters = 0
        for it in range(1, max_iter + 1):
            gram_cache.clear()
            chans = np.flatnonzero(active)
            prev = obj_t.copy()
            # plain block steps: rho, then scale (x follows below); per-channel decisions compare the objective
            # with the quadratic prior in use (for edges: the majoriser at the tangent point, so F decreases too)
            rho_p = rho_step(rho, S, chans)
            obj_r = J.objective(rho_p, X, S)
            Xs, Ss = X.copy(), [s.copy() for s in S]
            if gn is not None:
                # subspace Gauss-Newton proposals for x, each followed by the exact rho-step; kept while they beat
                # the plain rho-step (the same x-step follows either way, so the objective stays monotone)
                t0 = time.perf_counter()
                todo_ch = list(chans)
                for inner in range(gn_inner):
                    if not todo_ch:
                        break
                    b_rho, b_X, b_S = (rho, X, S) if inner == 0 else (rho_p, Xs, Ss)
                    dX = gn.direction(b_rho, b_X, b_S, todo_ch)
                    remaining, improved = list(todo_ch), []
                    for t in (1.0, 0.5, 0.25):
                        if not remaining:
                            break
                        Xt = b_X.copy()
                        Xt[:, :, remaining] = np.maximum(b_X[:, :, remaining] + t * dX[:, :, remaining], 0.0)
                        St = J.shading(Xt)
                        rt = rho_step(b_rho, St, np.array(remaining))
                        ot = J.objective(rt, Xt, St)
                        for c in list(remaining):
                            if ot[c] < obj_r[c]:
                                remaining.remove(c)
                                # keep going only while a proposal still buys a useful decrease
                                if obj_r[c] - ot[c] > 10 * tol * obj_r[c]:
                                    improved.append(c)
                                Xs[:, :, c] = Xt[:, :, c]
                                for k in range(P):
                                    Ss[k][:, :, c] = St[k][:, :, c]
                                    rho_p[k][:, c] = rt[k][:, c]
                                obj_r[c] = ot[c]
                                stats["gn_accepted"] += 1
                    stats["gn_rejected"] += len(remaining)
                    todo_ch = improved
                timers["gn"] += time.perf_counter() - t0
            step_hist.append(total(rho_p, Xs, Ss))
            if exact and scale_step:
                scale(rho_p, Xs, Ss, chans)
                step_hist.append(total(rho_p, Xs, Ss))
            J.tangent(Xs)
            obj_s = J.objective(rho_p, Xs, Ss)
            plain = list(chans)
            new_X, new_kkt = Xs, kkt_x.copy()
            new_rho = [r.copy() for r in rho_p]
            if accelerate:
                cand = [r.copy() for r in rho_p]
                tried = []
                for c in chans:
                    z = aa[c].step(flat(rho, c), flat(rho_p, c))
                    if z is not None:
                        z = np.clip(z, J.rho_min, 1.0)
                        z = np.where(fixed_flat, flat(rho_p, c), z)  # extrapolate the free pixels only
                        if np.max(np.abs(z - flat(rho_p, c))) > 1e-12:
                            unflat(z, cand, c)
                            tried.append(c)
                if tried:
                    Xa, ka = x_step(cand, Xs, np.array(tried), warm=True)
                    Sa = J.shading(Xa)
                    obj_a = J.objective(cand, Xa, Sa)
                    for c in tried:
                        if obj_a[c] <= obj_s[c]:
                            plain.remove(c)
                            new_X[:, :, c] = Xa[:, :, c]
                            new_kkt[:, c] = ka[:, c]
                            unflat(flat(cand, c), new_rho, c)
                            stats["accepted"] += 1
                        else:
                            aa[c].reset()
                            stats["rejected"] += 1
            if plain:
                Xp, kp = x_step(new_rho, Xs, np.array(plain), warm=True)
                if fast_gram and exact and not use_pcg:
                    # the float32 Gram could in principle cost a hair of objective: check, redo in float64
                    obj_p = J.objective(new_rho, Xp, J.shading(Xp))
                    redo = [c for c in plain if obj_p[c] > obj_s[c]]
                    if redo:
                        X64, k64 = x_step(new_rho, Xs, np.array(redo), warm=True, fast=False)
                        for c in redo:
                            Xp[:, :, c], kp[:, c] = X64[:, :, c], k64[:, c]
                        stats["float64_redo"] += len(redo)
                for c in plain:
                    new_X[:, :, c] = Xp[:, :, c]
                    new_kkt[:, c] = kp[:, c]
            rho, X, kkt_x = new_rho, new_X, new_kkt
            if J.huber_on and exact:
                # more majorise-minimise x-steps on this sweep's Gram matrices (factorisations only): each one
                # minimises the majoriser at the current point exactly, so F decreases
                step_hist.append(total(rho, X, J.shading(X)))
                for _ in range(edge_steps - 1):
                    J.tangent(X)
                    Xm, km = x_step(rho, X, chans, warm=True)
                    Sm = J.shading(Xm)
                    fm, fx = total(rho, Xm, Sm), step_hist[-1]
                    stats["mm_steps"] += 1
                    if not fm <= fx:  # float32 Gram rounding: keep the better point
                        break
                    X, kkt_x = Xm, km
                    step_hist.append(fm)
                    if fx - fm <= 0.1 * tol * fx:
                        break
            J.tangent(X)
            S = J.shading(X)
            obj_t = J.true_objective(rho, X, S)
            tot = float(obj_t.sum())
            step_hist.append(tot)
            hist.append(obj_t.copy())
            iters = it
            # ---- divergence guard
            if np.isfinite(tot) and tot < best[0]:
                best = (tot, X.copy(), [r.copy() for r in rho], [s.copy() for s in S], obj_t.copy(),
                        kkt_x.copy(), it)
            if not np.isfinite(tot) or tot > diverge_factor * best[0]:
                why = ("non-finite objective" if not np.isfinite(tot) else
                       f"objective {tot:.6g} > {diverge_factor:g} x best {best[0]:.6g}")
                diverged = True
                message = (f"diverged at sweep {it} ({why}); returning the last good estimate, from sweep "
                           f"{best[6]} (objective {best[0]:.6g})")
                break
            if per_channel:
                dec = (prev - obj_t) / np.where(prev > 0, prev, 1.0)
                done = np.abs(dec) < tol if not exact else dec < tol
            else:
                p_tot = float(prev.sum())
                dec_t = (p_tot - tot) / (p_tot if p_tot > 0 else 1.0)
                done = np.full(C, abs(dec_t) < tol if not exact else dec_t < tol)
            active &= ~done
            if not active.any():
                break
        converged = (not diverged) and not active.any()
        if diverged:
            _, X, rho, S, obj_t, kkt_x, _ = best
        elif exact and polish and (fast_gram or use_pcg or J.huber_on):
            # final x-step (for edges: at the final tangent point), polished against the exact float64 operator with
            # the last sweep's float32 Gram matrices (formed at this albedo) as the preconditioner: x exactly optimal
            # (KKT ~ qp_tol) for the final rho and the quadratic prior in use
            J.tangent(X)
            pre = {c: J.gram(rho, c, gram_cache, fast=fast_gram) for c in range(C)}  # cached: no new Gram
            Xf, kf = x_step_pcg(rho, X, np.arange(C), warm=True, grams=pre)
            Sf = J.shading(Xf)
            ff = total(rho, Xf, Sf)
            if ff <= step_hist[-1] * (1 + 1e-12):
                X, kkt_x, S = Xf, kf, Sf
                obj_t = J.true_objective(rho, X, S)
                step_hist.append(float(obj_t.sum()))
                hist[-1] = obj_t.copy()
        if not message:
            message = (f"converged after {iters} sweeps (relative decrease < {tol:g})" if converged else
                       f"stopped at max_iter = {max_iter} sweeps before the relative decrease fell below {tol:g}")
        kkt_rho = J.rho_kkt(rho, S)
        rmax = np.max([r.max(axis=0) for r in rho if r.shape[0]], axis=0)
    hist_arr = np.array(hist)
    above = float(np.mean(J.edge_norms(X) > J.edge_thr[:, None])) if J.huber_on else 0.0
    if J.basis is not None:
        X = (J.basis @ X.reshape(n, -1)).reshape(-1, L, C)
    return JointResult(
        x=X,
        rho=rho,
        objective=obj_t,
        history=hist_arr.sum(axis=1),
        history_channels=hist_arr,
        step_history=step_hist,
        iterations=iters,
        converged=converged,
        diverged=diverged,
        message=message,
        kkt_x=kkt_x,
        kkt_rho=kkt_rho,
        scale_ambiguous=not J.any_fixed,
        scale_at_clip=rmax >= 1.0 - 1e-12,
        method=method,
        seconds=time.perf_counter() - t_start,
        info=dict(
            ls_abs=J.ls, lr_abs=J.lr, lp_abs=J.lp, **J.rel,
            data_scale=J.s_data, albedo_data_scale=J.t_data,
            gram_seconds=J.t_gram, grams=J.grams, x_step_seconds=timers["x"], rho_step_seconds=timers["rho"],
            anderson_accepted=stats["accepted"], anderson_rejected=stats["rejected"],
            float64_redo=stats["float64_redo"], gn_accepted=stats["gn_accepted"], gn_rejected=stats["gn_rejected"],
            gn_seconds=timers["gn"], gn_rank=0 if gn is None else gn.k, scale_seconds=timers["scale"],
            xsolver=xsolver if exact else "gram", x_steps=ref["steps"], reference_grams=ref["refreshes"],
            operator_applications=ref["applications"], pivot_rounds=ref["rounds"],
            prior=prior if J.huber_on or prior == "smooth" else "smooth (edges: no edge scale)",
            edge_scale=J.edge_s.tolist(), edge_eps=J.edge_eps_rel, mm_steps=stats["mm_steps"],
            edges_above_threshold=above,
        ),
    )


def joint_objective(
    blocks: Sequence[CameraBlock | tuple],
    grid: EnvGrid,
    texel_index: np.ndarray,
    x: np.ndarray,
    rho: Sequence[np.ndarray],
    ls: float = DEFAULT_LS_REL,
    lr: float = DEFAULT_LR_REL,
    lp: float = 0.0,
    relative: bool = True,
    prior: str = "smooth",
    edge_scale: Sequence[float] | None = None,
    edge_eps: float = 0.05,
) -> np.ndarray:
    """The objective per channel (C,) of :func:`solve_joint` at (x (N, L, C), rho list of (M_p, C)).

    prior="edges" needs the Huber scale per target that the solve fixed (``JointResult.info["edge_scale"]``); the
    shared edge term is split equally between the channels (as :attr:`JointResult.objective`)."""
    J = _Joint(blocks, grid, texel_index, ls, lr, lp, relative, DEFAULT_RHO_MIN, prior=prior, edge_eps=edge_eps)
    X = np.asarray(x, dtype=np.float64).reshape(J.n, J.L, J.C)
    rho = [np.asarray(r, dtype=np.float64).reshape(-1, J.C) for r in rho]
    if prior == "edges":
        if edge_scale is None:
            raise ValueError("prior='edges' needs edge_scale (JointResult.info['edge_scale'])")
        J.edge_s = np.asarray(edge_scale, dtype=np.float64).reshape(J.L)
        J.edge_thr = J.edge_eps_rel * J.edge_s
        J.huber_on = bool(np.all(J.edge_s > 0))
    with single_blas_thread():
        return J.true_objective(rho, X, J.shading(X))


# ------------------------------------------------------------------------------------------------ evaluation


def scatter_envmaps(x: np.ndarray, grid: EnvGrid, texel_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L, H, W, C) envmaps from x (N, L, C) (texels not kept are 0) and the (H, W) kept mask."""
    x = np.asarray(x, dtype=np.float64)
    n, nl, nc = x.shape
    env = np.zeros((nl, grid.n_texels, nc))
    env[:, texel_index, :] = np.transpose(x, (1, 0, 2))
    mask = np.zeros(grid.n_texels, dtype=bool)
    mask[texel_index] = True
    return env.reshape(nl, grid.height, grid.width, nc), mask.reshape(grid.shape)


def _ls_scale(est: np.ndarray, truth: np.ndarray) -> float:
    ee = float(np.sum(est * est))
    return float(np.sum(est * truth) / ee) if ee > 0 else 1.0


def evaluate_joint(
    x: np.ndarray,
    rho: Sequence[np.ndarray],
    x_true: np.ndarray,
    rho_true: Sequence[np.ndarray],
    grid: EnvGrid,
    texel_index: np.ndarray,
    per_channel: bool = True,
) -> dict[str, Any]:
    """Errors of a joint estimate after the best-fit scale that the scale ambiguity leaves free.

    x, x_true: (N, L, C); rho, rho_true: lists of (M_p, C). With ``per_channel`` (default; the ambiguity is one
    scale per channel) the envmaps of channel c are multiplied by the least-squares scale k_c over all targets and
    kept texels, and the albedo by its own least-squares scale; otherwise one scale over all channels, as
    :func:`objcam.metrics.best_scale`. Returns ``env_scale`` (C,), ``env_rel_rmse`` (L,) (objcam.metrics
    relative RMSE per target, kept texels), ``rho_scale`` (C,), ``rho_rel_rmse`` (RMSE / mean(truth), all
    cameras and channels) and ``scale_product`` = env_scale * rho_scale (~1 for a consistent estimate).
    """
    x = np.asarray(x, dtype=np.float64)
    x_true = np.asarray(x_true, dtype=np.float64)
    nc = x.shape[2]
    r_est = np.concatenate([np.asarray(r, dtype=np.float64).reshape(-1, nc) for r in rho])
    r_true = np.concatenate([np.asarray(r, dtype=np.float64).reshape(-1, nc) for r in rho_true])
    if per_channel:
        kx = np.array([_ls_scale(x[:, :, c], x_true[:, :, c]) for c in range(nc)])
        kr = np.array([_ls_scale(r_est[:, c], r_true[:, c]) for c in range(nc)])
    else:
        kx = np.full(nc, _ls_scale(x, x_true))
        kr = np.full(nc, _ls_scale(r_est, r_true))
    est_env, mask = scatter_envmaps(x * kx, grid, texel_index)
    true_env, _ = scatter_envmaps(x_true, grid, texel_index)
    env_err = np.array([relative_rmse(est_env[l], true_env[l], mask) for l in range(x.shape[1])])
    rs = r_est * kr
    rho_err = float(np.sqrt(np.mean((rs - r_true) ** 2)) / np.mean(r_true))
    return dict(env_scale=kx, env_rel_rmse=env_err, rho_scale=kr, rho_rel_rmse=rho_err, scale_product=kx * kr)
