"""Automatic choice of the regularisation weights for the known-albedo problem.

    min_x ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2      (x >= 0 in the final solve)

Three rules, all evaluated on the *unconstrained* ridge solution ``x(ls) = Q^{-1} A^T y``,
``Q = A^T A + ls D^T D + lr I``: the non-negativity constraint is ignored by the criteria (they need the
solution to be linear in y) and applied only in the final solve (:func:`objcam.solvers.solve_envmap` with the
chosen weights). Y may hold several columns (channels, targets); the criteria pool them (one weight pair for all).

- ``"gcv"`` -- generalised cross-validation (Golub, Heath & Wahba 1979): minimise
  ``GCV(ls) = (||A X - Y||_F^2 / (M k)) / (1 - tr(H)/M)^2`` with k columns and the influence matrix
  ``H = A Q^{-1} A^T``, ``tr(H) = tr(Q^{-1} A^T A)``. Needs no noise level.
- ``"discrepancy"`` -- Morozov's discrepancy principle from the noise model: the largest ls with
  ``||A X - Y||_F^2 <= tau E`` (E: the noise energy, ``M k sigma^2`` for Gaussian noise of std sigma, times
  ``mean(y) / median(y)`` for photon noise whose sigma is quoted at the median pixel; tau = 1 by default). The
  residual grows monotonically with ls, so the largest admissible ls is found on the grid and refined by bisection
  in log ls. With model error (A is a model of the renderer: on path-traced targets its error, 1-5% near the
  object, exceeds a 0.2% noise) no ls meets that target and every rule that trusts the residual (GCV, the plain
  discrepancy, also UPRE) picks the smallest ls, because the model error is partly fittable by more degrees of
  freedom. So the residual of the nearly unregularised fit (the smallest ls of the grid) is taken as the floor the
  model cannot go below, and the regularisation may cost the noise energy above it: ``residual <= floor + tau E``
  (``model_error=True``, default; with pure noise the floor is below E and the classic rule applies).
  Measured against the best hand-tuned ls per bundled HDRI in bench/results.md ("Joint solve ablation").
- ``"lcurve"`` -- the corner of the L-curve (Hansen): the point of maximum curvature of
  ``(log ||A x - y||, log ||D x||)`` as a function of log ls.

Fast evaluation (one O(N^3) decomposition per lr, then O(N^2 k) per ls). With ``K = A^T A`` and ``L = D^T D``,
solve the symmetric-definite generalised eigenproblem ``L v = nu (K + lr I) v`` (scipy.linalg.eigh), normalised
so that ``V^T (K + lr I) V = I`` and ``V^T L V = diag(nu)``, nu >= 0. Then for every ls

    Q^{-1} = V diag(1 / (1 + ls nu)) V^T,  x = V d  with  d = c / (1 + ls nu),  c = V^T A^T y,
    tr(Q^{-1} K) = sum_j (1 - lr ||v_j||^2) / (1 + ls nu_j)           (V^T K V = I - lr V^T V),
    ||A x - y||^2 = y^T y - 2 c^T d + d^T (I - lr V^T V) d,
    ||D x||^2 = sum_j nu_j d_j^2,   ||x||^2 = d^T (V^T V) d,

so the trace is O(N) and the residual O(N^2) per column (the lr term; O(N) when lr = 0). ``lr`` must be > 0
for K + lr I to be definite (the default grid point is :data:`objcam.solvers.DEFAULT_LR_REL`); a 2-D search
passes several ``lr_grid`` values, one decomposition each (GCV only: it compares across lr).

Weights are returned RELATIVE to ``s = mean(diag(A^T A))`` (the convention of
:mod:`objcam.solvers.regularization`); internally ``ls_abs = ls_rel * s``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg as sla

from objcam.envmap import EnvGrid
from objcam.solvers.regularization import DEFAULT_LR_REL, data_scale, difference_operator, gram, rhs
from objcam.solvers.search import golden_section
from objcam.threads import single_blas_thread

#: Default relative ls grid: 1e-7 .. 1e2, 10 points per decade.
DEFAULT_LS_GRID = np.logspace(-7, 2, 91)

RULES = ("gcv", "discrepancy", "lcurve")


@dataclass
class SpectralSystem:
    """The generalised eigen-decomposition of (D^T D, A^T A + lr I) and the data projected on it.

    nu (N,) >= 0; V (N, N) with V^T (K + lr I) V = I; vtv = V^T V (N, N); c = V^T A^T Y (N, k); yTy (k,);
    m = number of pixels; lr = absolute ridge weight; seconds = time of the decomposition.
    """

    nu: np.ndarray
    V: np.ndarray
    vtv: np.ndarray
    c: np.ndarray
    yTy: np.ndarray
    m: int
    lr: float
    seconds: float

    def evaluate(self, ls: float) -> dict[str, Any]:
        """Residual (k,), ||D x||^2 (k,), ||x||^2 (k,), tr(H) and GCV at absolute ``ls`` (unconstrained x)."""
        f = 1.0 / (1.0 + ls * self.nu)
        d = self.c * f[:, None]
        Wd = self.vtv @ d
        xx = np.einsum("nk,nk->k", d, Wd)
        res = self.yTy - 2.0 * np.einsum("nk,nk->k", self.c, d) + np.einsum("nk,nk->k", d, d) - self.lr * xx
        res = np.maximum(res, 0.0)
        dx = np.einsum("n,nk->k", self.nu, d * d)
        tr = float(np.sum((1.0 - self.lr * np.diag(self.vtv)) * f))
        k = self.c.shape[1]
        denom = (1.0 - tr / self.m) ** 2
        gcv = float(res.sum() / (self.m * k) / denom) if tr < self.m else float("inf")
        return dict(residual=res, dx2=dx, x2=xx, trace=tr, gcv=gcv)

    def solution(self, ls: float) -> np.ndarray:
        """The unconstrained ridge solution x (N, k) at absolute ``ls``."""
        return self.V @ (self.c / (1.0 + ls * self.nu)[:, None])


def spectral_system(K: np.ndarray, Lmat: np.ndarray, B: np.ndarray, yTy: np.ndarray, m: int, lr: float
                    ) -> SpectralSystem:
    """Decompose for fast criteria: ``K = A^T A`` (N, N), ``Lmat = D^T D`` dense (N, N), ``B = A^T Y`` (N, k),
    ``yTy`` (k,), m pixels, absolute ``lr > 0``."""
    if lr <= 0:
        raise ValueError("the fast criteria need lr > 0 (K + lr I must be positive definite)")
    t0 = time.perf_counter()
    n = K.shape[0]
    with single_blas_thread():
        Kr = K + lr * np.eye(n)
        nu, V = sla.eigh(Lmat, Kr, check_finite=False)
        nu = np.maximum(nu, 0.0)
        vtv = V.T @ V
        c = V.T @ B
    return SpectralSystem(nu, V, vtv, c, np.asarray(yTy, dtype=np.float64), m, lr, time.perf_counter() - t0)


def gcv_brute_force(K: np.ndarray, Lmat: np.ndarray, B: np.ndarray, yTy: np.ndarray, m: int, ls: float,
                    lr: float) -> float:
    """GCV at absolute (ls, lr) by forming Q and solving directly (reference for the fast evaluation)."""
    Q = K + ls * Lmat + lr * np.eye(K.shape[0])
    X = np.linalg.solve(Q, B)
    res = yTy - 2 * np.einsum("nk,nk->k", B, X) + np.einsum("nk,nk->k", X, K @ X)
    tr = float(np.trace(np.linalg.solve(Q, K)))
    return float(res.sum() / (m * B.shape[1]) / (1 - tr / m) ** 2)


def _curvature(t: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Signed curvature of the plane curve (a(t), b(t)) sampled on t (finite differences)."""
    da, db = np.gradient(a, t), np.gradient(b, t)
    dda, ddb = np.gradient(da, t), np.gradient(db, t)
    return (da * ddb - dda * db) / np.maximum((da * da + db * db) ** 1.5, 1e-300)


def choose_weights(
    A: np.ndarray,
    Y: np.ndarray,
    grid: EnvGrid,
    texel_index: np.ndarray,
    rule: str = "gcv",
    sigma: float | None = None,
    ls_grid: np.ndarray | None = None,
    lr: float = DEFAULT_LR_REL,
    lr_grid: np.ndarray | None = None,
    tau: float = 1.0,
    refine: bool = True,
    model_error: bool = True,
    noise_model: str = "shot",
) -> tuple[float, float, dict[str, Any]]:
    """Choose (ls_rel, lr_rel) for ``min ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2`` by ``rule``.

    A: (M, N) transport (albedo included); Y: (M,), (M, k) or (M, L, C) pixel values (columns pooled);
    grid, texel_index: the envmap grid and the kept texels (columns of A), for D.
    rule: "gcv", "discrepancy" (needs ``sigma``, the noise standard deviation of one pixel value; ``tau``) or
        "lcurve".
    noise_model: "shot" (default; ``sigma`` is the noise of the median pixel and the variance grows with the
        value, as photon noise: the expected noise energy is ``M k sigma^2 mean(y) / median(y)``) or "gaussian"
        (the same sigma everywhere: ``M k sigma^2``).
    model_error: discrepancy only: when even the smallest ls leaves a residual above the noise energy (the model
        misses the photo by more than its noise: model error), measure the discrepancy from that floor, i.e. take
        the largest ls with ``residual <= floor + tau x noise energy`` (see the module docstring).
    ls_grid: relative ls values searched (default :data:`DEFAULT_LS_GRID`, 1e-7..1e2); ``refine`` then polishes
        the choice between grid points (golden section in log ls for GCV, bisection for the discrepancy,
        a 10x denser grid for the L-curve).
    lr: the fixed relative ridge weight (> 0); ``lr_grid``: several lr values for a 2-D search (GCV only).

    Returns ``(ls_rel, lr_rel, info)``: relative weights (multiples of mean(diag(A^T A))) and an info dict with
    the rule, the grid, the criterion values on it (``criterion``), residuals, traces, ``||D x||``,
    the data scale, timings and notes (e.g. ``"no ls meets the discrepancy"``). The criteria use the
    unconstrained ridge solution (see the module docstring). Raises ValueError on M = 0 or bad arguments.
    """
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
    A = np.asarray(A)
    if A.ndim != 2:
        raise ValueError(f"A must be 2-D, got {A.shape}")
    m, n = A.shape
    if m == 0:
        raise ValueError("choose_weights: no valid pixels (M = 0) -- nothing to choose the weights from")
    Y2 = np.asarray(Y, dtype=np.float64).reshape(m, -1)
    if rule == "discrepancy" and (sigma is None or not sigma > 0):
        raise ValueError("the discrepancy rule needs the noise standard deviation sigma > 0")
    if noise_model not in ("shot", "gaussian"):
        raise ValueError(f"noise_model must be 'shot' or 'gaussian', got {noise_model!r}")
    pos = Y2[Y2 > 0]
    shot = float(np.mean(Y2) / np.median(pos)) if (noise_model == "shot" and pos.size) else 1.0
    ls_grid = np.asarray(DEFAULT_LS_GRID if ls_grid is None else ls_grid, dtype=np.float64)
    if ls_grid.ndim != 1 or ls_grid.size < 3 or np.any(ls_grid <= 0):
        raise ValueError("ls_grid must hold at least 3 positive values")
    ls_grid = np.sort(ls_grid)
    lrs = np.atleast_1d(np.asarray(lr if lr_grid is None else lr_grid, dtype=np.float64))
    if np.any(lrs <= 0):
        raise ValueError("lr must be > 0 for the fast criteria")
    if rule != "gcv" and lrs.size > 1:
        raise ValueError("a 2-D (lr_grid) search is only defined for rule='gcv'")

    t0 = time.perf_counter()
    with single_blas_thread():
        K = gram(A)
        B = rhs(A, Y2)
    yTy = np.einsum("mk,mk->k", Y2, Y2)
    s = data_scale(K)
    if s <= 0:
        raise ValueError("A is all zero: nothing constrains the envmap")
    D = difference_operator(grid, texel_index)
    Lmat = (D.T @ D).toarray()
    t_form = time.perf_counter() - t0
    k = Y2.shape[1]
    log_grid = np.log(ls_grid)
    info: dict[str, Any] = dict(rule=rule, ls_grid=ls_grid, data_scale=s, form_seconds=t_form, notes=[],
                                nonnegativity="ignored by the criterion (unconstrained ridge); apply it in the solve")

    def curve(sysm: SpectralSystem, rel: np.ndarray) -> dict[str, np.ndarray]:
        ev = [sysm.evaluate(v * s) for v in rel]
        return dict(
            gcv=np.array([e["gcv"] for e in ev]),
            residual=np.array([e["residual"].sum() for e in ev]),
            trace=np.array([e["trace"] for e in ev]),
            dx2=np.array([e["dx2"].sum() for e in ev]),
        )

    best = None
    decomp_s = 0.0
    per_lr = []
    for lr_rel in lrs:
        sysm = spectral_system(K, Lmat, B, yTy, m, float(lr_rel) * s)
        decomp_s += sysm.seconds
        cv = curve(sysm, ls_grid)
        per_lr.append(dict(lr_rel=float(lr_rel), **cv))
        if rule == "gcv":
            j = int(np.argmin(cv["gcv"]))
            t_best, v_best = log_grid[j], cv["gcv"][j]
            if refine and 0 < j < ls_grid.size - 1:
                f = lambda t: sysm.evaluate(np.exp(t) * s)["gcv"]  # noqa: E731
                t, v = golden_section(f, log_grid[j - 1], log_grid[j + 1], tol=1e-4)
                if v < v_best:
                    t_best, v_best = t, v
            if j in (0, ls_grid.size - 1):
                info["notes"].append(f"GCV minimum at the edge of the ls grid (lr_rel={lr_rel:g})")
            if best is None or v_best < best[0]:
                best = (v_best, float(np.exp(t_best)), float(lr_rel), cv)
        elif rule == "discrepancy":
            noise = tau * m * sigma**2 * k * shot
            target = noise
            floor = float(cv["residual"][0])
            if model_error and floor > target:
                # the nearly unregularised fit already misses by more than the noise: model error (A is not the
                # renderer) that no ls can remove. Let the regularisation cost the noise energy above that floor.
                target = floor + noise
                info["notes"].append(f"residual floor {floor:.4g} above the noise energy {noise:.4g} (model error): "
                                     "discrepancy measured from the floor")
            info["residual_floor"] = floor
            info["noise_energy"] = noise
            ok = cv["residual"] <= target
            if not ok.any():
                j = 0
                t_best = log_grid[0]
                info["notes"].append("no ls on the grid meets the discrepancy (residual > tau M sigma^2): "
                                     "took the smallest; sigma may be underestimated")
            elif ok.all():
                j = ls_grid.size - 1
                t_best = log_grid[-1]
                info["notes"].append("every ls on the grid meets the discrepancy: took the largest; sigma may be "
                                     "overestimated")
            else:
                j = int(np.flatnonzero(ok)[-1])
                t_best = log_grid[j]
                if refine:
                    a_, b_ = log_grid[j], log_grid[j + 1]  # res(a) <= target < res(b)
                    while b_ - a_ > 1e-6:
                        mid = 0.5 * (a_ + b_)
                        if sysm.evaluate(np.exp(mid) * s)["residual"].sum() <= target:
                            a_ = mid
                        else:
                            b_ = mid
                    t_best = a_
            info["target_residual"] = target
            best = (0.0, float(np.exp(t_best)), float(lr_rel), cv)
        else:  # lcurve
            if refine:
                tt = np.linspace(log_grid[0], log_grid[-1], 10 * ls_grid.size)
                cvd = curve(sysm, np.exp(tt))
            else:
                tt, cvd = log_grid, cv
            rho_ = 0.5 * np.log(np.maximum(cvd["residual"], 1e-300))
            eta = 0.5 * np.log(np.maximum(cvd["dx2"], 1e-300))
            kap = _curvature(tt, rho_, eta)
            kap[[0, -1]] = -np.inf
            j = int(np.argmax(kap))
            info["lcurve_curvature"] = kap
            info["lcurve_log_ls"] = tt
            best = (0.0, float(np.exp(tt[j])), float(lr_rel), cv)
            if j in (1, tt.size - 2):
                info["notes"].append("L-curve corner at the edge of the ls grid")
    _, ls_rel, lr_rel, cv = best
    info.update(criterion=cv["gcv"] if rule == "gcv" else (cv["residual"] if rule == "discrepancy" else cv["dx2"]),
                gcv=cv["gcv"], residual=cv["residual"], trace=cv["trace"], dx2=cv["dx2"],
                per_lr=per_lr, decomposition_seconds=decomp_s, seconds=time.perf_counter() - t0,
                ls_abs=ls_rel * s, lr_abs=lr_rel * s)
    return ls_rel, lr_rel, info
