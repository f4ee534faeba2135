"""The two safeguarded accelerations of the exact alternation: subspace Gauss-Newton and Anderson.

Plain alternation is slow here: a smooth change of the albedo can be traded against a change of the envmaps
almost for free, and exact block steps crawl along that valley (rate 0.92-0.99 per sweep on test scenes; hundreds
of sweeps at N = 1024). Two safeguarded accelerations make it converge in ~10-25 sweeps, and neither can raise the
objective, because each only proposes a point and the proposal is kept only if it beats the plain block step it
replaces (the alternation, :mod:`objcam.solvers.joint.alternation`, makes that comparison):

* subspace Gauss-Newton (:class:`SubspaceGN`, ``gn_rank`` = k, default 128; 0 disables): before the rho-step,
  a variable-projection Gauss-Newton step for x restricted to the top-k eigenvectors of the first x-step's Gram
  matrix (with each target's active texels held at 0), followed by the exact rho-step at the new x; kept if it beats
  the exact rho-step at the old x (backtracking 1, 1/2, 1/4). Costs L(L+1)/2 weighted k x k Gram matrices of
  ``A' V`` per channel, a few percent of one N x N Gram;
* Anderson acceleration (:class:`Anderson`, type II, depth 5) of the albedo sequence: the extrapolated albedo is
  tried with its exact x-step and kept if its objective is below that after the plain rho and scale steps (an
  extra x-step when it is not).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_solve
from scipy.sparse.linalg import splu

from objcam.solvers.joint.kernels import chol, matmul, weighted_gram
from objcam.solvers.joint.problem import JointProblem
from objcam.threads import parallel_map


class SubspaceGN:
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

    def __init__(self, J: JointProblem, k: int, fast: bool, K: np.ndarray | None = None):
        self.J = J
        n = J.n
        self.k = k = int(min(k, n))
        if K is None:
            K = weighted_gram(J.As, [np.ones(A.shape[0]) for A in J.As], n, fast=fast)
        evals, evecs = np.linalg.eigh(K)
        self.V = np.ascontiguousarray(evecs[:, ::-1][:, :k])
        self.V32 = self.V.astype(np.float32)
        self.B = [(A64 @ self.V if A64 is not None else matmul(A, self.V)).astype(np.float32)
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
        free = np.flatnonzero((r > J.rho_min) & (r < 1.0) & ~J.held(p))  # a group's pixels held here
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
        grp: dict[int, list] = {int(g): [np.zeros(L * k), 0.0, 0.0, 0.0] for g in J.group_ids}  # u, h, q, value
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
            free = (a > 1e-12 * (a.max() if a.size else 1.0)) & (r > J.rho_min) & (r < 1.0) & ~J.held(p)
            for gid, acc in grp.items():  # a group's albedo is eliminated once over all its pixels, below
                sel = J.groups[p] == gid
                if sel.any():
                    rg = float(r[sel][0])
                    for l in range(L):
                        acc[0][l * k:(l + 1) * k] += rg * (Bl[l][p][sel].T.astype(np.float64) @ s[sel, l])
                    acc[1] += float(np.sum(s[sel] ** 2))
                    acc[2] += float(np.sum(s[sel] * res[sel]))
                    acc[3] = rg
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
        for u, h, q, rg in grp.values():
            # variable projection over the group's one albedo: the Schur complement of its 1 x 1 block
            # (objcam.solvers.joint.groups), unless it sits at a bound (held there, as a pixel's)
            if h > 0 and J.rho_min < rg < 1.0 and J.lp == 0:
                H -= np.outer(u, u) / h
                g -= u * (q / h)
        H = 0.5 * (H + H.T)
        try:
            fac, _ = chol(H)
            dz = -cho_solve(fac, g, check_finite=False)
        except np.linalg.LinAlgError:
            return None
        return np.stack([Vl[l] @ dz[l * k:(l + 1) * k] for l in range(L)], axis=1)


class Anderson:
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
