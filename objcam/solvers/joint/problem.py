"""The joint problem: its prepared data, its objective and the per-channel kernels every block step uses.

Model. Camera p (p = 1..P) sees M_p valid pixels; its rho-free light transport is ``A'_p`` (M_p, N) (the same N
kept envmap texels for every camera) and its per-pixel albedo ``rho_p`` (M_p, C), one value per colour channel.
The photo of target (illumination) l in channel c is ``y_plc = diag(rho_pc) A'_p x_lc`` with ``x_lc`` (N,) the
envmap radiance. Colour channels never interact (rho, x and y are all per channel; only the grey A' is shared),
so everything below is per channel c; the objective reported is the sum over channels:

    F_c(rho, x) = sum_{p,l} ||diag(rho_pc) A'_p x_lc - y_plc||^2                      (data)
                + sum_l ( ls ||D x_lc||^2 + lr ||x_lc||^2 )                             (envmap prior)
                + lp sum_p ||G_p rho_pc||^2                                              (albedo prior)
      subject to  x_lc >= 0,   rho_min <= rho_pc <= 1.

G_p is the albedo regulariser of :mod:`objcam.solvers.joint.blocks` (first differences on the image grid).

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
channel, so every per-channel block step applies unchanged, and a step that lowers the majoriser lowers F.
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
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from objcam.solvers.basis import group_sizes
from objcam.solvers.joint.albedo import albedo_normal
from objcam.solvers.joint.blocks import (
    DEFAULT_RHO0,
    NoValidPixelsError,
    albedo_smoothness_operator,
    as_camera_block,
    photos_mlc,
)
from objcam.solvers.joint.boxqp import box_kkt_residual
from objcam.solvers.joint.groups import check_groups, group_kkt, group_terms, unify, values_of
from objcam.solvers.joint.kernels import col_sq_norms, matmul, tmatmul, weighted_gram
from objcam.solvers.regularization import difference_operator
from objcam.threads import blas_threads

#: Largest A' of which float64 and transposed float32 copies are kept (bigger ones are converted block by block).
_COPY_BYTES = 2 * 2**30

#: Envmap priors: quadratic smoothness, or the edge-preserving Huber prior (objcam.solvers.edges' model).
PRIORS = ("smooth", "edges")


class JointProblem:
    """Prepared data and the per-channel kernels of the joint problem.

    Holds per camera p the transport ``As[p]`` (M_p, N) (merged to the basis' N columns when one is given), its
    float64 copy ``A64[p]`` (None when too large), the photos ``Ys[p]`` (M_p, L, C), the albedo operator ``Gs[p]``
    (E_p, M_p) and the known-albedo mask ``fixed[p]`` (M_p,); the envmap difference operator ``D`` (E, N); the
    absolute weights ``ls, lr, lp``; and the envmap prior in use: per-edge weights ``W`` (L, E) (1 for the
    quadratic prior, the Huber majoriser's at the tangent point for the edge prior).
    """

    def __init__(self, blocks, grid, texel_index, ls, lr, lp, relative, rho_min, prior="smooth", edge_eps=0.05,
                 basis: sp.spmatrix | None = None):
        blocks = [as_camera_block(b) for b in blocks]
        if not blocks:
            raise NoValidPixelsError("joint solve: no camera blocks given -- nothing constrains the envmap")
        texel_index = np.asarray(texel_index, dtype=np.int64).ravel()
        self.n = n = texel_index.size
        self.As, self.Ys, self.Gs, self.rho0, self.fixed, self.groups = [], [], [], [], [], []
        shape_lc = None
        for k, b in enumerate(blocks):
            A = np.asarray(b.A)
            if A.ndim != 2 or A.shape[1] != n:
                raise ValueError(f"camera {k}: A' is {A.shape}, expected (M, {n}) for {n} kept texels")
            Y = photos_mlc(b.Y)
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
            self.groups.append(check_groups(b.groups, A.shape[0], fx, k))
        self.group_ids = np.unique(np.concatenate([g[g > 0] for g in self.groups]))
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
        self.s_data = float(np.mean(sum(col_sq_norms(A) for A in self.As)))
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
        return unify(out, self.groups, self.group_ids, self.rho_min)

    def pin(self, rho: list[np.ndarray]) -> list[np.ndarray]:
        """Hold the fixed pixels at their albedo and give each group one albedo (its mean) (in place); returns
        rho."""
        for k, fx in enumerate(self.fixed):
            if fx.any():
                rho[k][fx] = self.fixed_vals[k][fx]
        return unify(rho, self.groups, self.group_ids, self.rho_min)

    def held(self, k: int) -> np.ndarray:
        """(M_k,) bool: camera k's pixels whose albedo the per-pixel step leaves alone: known (fixed) or in a group
        (objcam.solvers.joint.groups updates those)."""
        return self.fixed[k] | (self.groups[k] > 0)

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
            return [(A64 @ Xf if A64 is not None else matmul(A, Xf)).reshape(A.shape[0], self.L, self.C)
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
                    out[:, j] += col_sq_norms(A, w[:, j])
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
                B[:, :, ch] += (A64.T @ U if A64 is not None else tmatmul(A, U)).reshape(self.n, self.L, ch.size)
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
        a, beta = albedo_normal(S_p[:, :, c], Y_p[:, :, c], rho_p[:, c] if prox else None)
        H = sp.diags(a) + self.lp * self.GtG[k] if self.lp > 0 else sp.diags(a)
        return sp.csr_matrix(H), beta

    def rho_kkt(self, rho, S) -> np.ndarray:
        """(P, C) relative KKT residual of the albedo subproblem at rho: per camera its pixels' box QP (a group's
        pixels held at their value), and each group's 1-D problem, charged to every camera holding it."""
        out = np.zeros((self.P, self.C))
        now = values_of(rho, self.groups)  # each group's albedo (C,)
        for c in range(self.C):
            parts: dict[int, list] = {int(g): [] for g in self.group_ids}
            scale = 0.0
            for k, (r, s, Y) in enumerate(zip(rho, S, self.Ys)):
                if not r.shape[0]:
                    continue
                H, beta = self.rho_system(r, s, Y, k, c, prox=False)
                lo, hi = self.bounds(k, c)
                gr = self.groups[k] > 0
                if gr.any():
                    lo, hi = np.where(gr, r[:, c], lo), np.where(gr, r[:, c], hi)
                    for g in parts:
                        sel = self.groups[k] == g
                        if sel.any():
                            parts[g].append(group_terms(H, beta, r[:, c], sel))
                out[k, c] = box_kkt_residual(H, beta, r[:, c], lo, hi)
                scale = max(scale, float(np.max(np.abs(beta))))
            if parts:
                gk = group_kkt(parts, {g: float(now[g][c]) for g in parts}, self.rho_min, scale)
                for k in range(self.P):
                    if (self.groups[k] > 0).any():
                        out[k, c] = max(out[k, c], gk)
        return out
