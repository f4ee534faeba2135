"""The method's baseline solver: damped Newton steps with clipping (the paper's Eq. 7).

    x_{k+1} = max(0, x_k - alpha Q^{-1} (Q x_k - b))

The step is the *unconstrained* Newton direction, so the iteration is ``x_{k+1} = max(0, (1 - alpha) x_k +
alpha Q^{-1} b)``: from x_0 = 0 it converges geometrically (rate 1 - alpha) to ``max(0, Q^{-1} b)``, the
clipped unconstrained solution -- not the constrained minimiser, whose objective is never higher (see
:func:`objcam.solvers.nnls.solve_exact`). Kept for comparison with the paper.
"""

from __future__ import annotations

import time

import numpy as np

from objcam.solvers.nnls import SolveResult, _as_2d, _Factor, kkt_residual, objective
from objcam.threads import single_blas_thread


def solve_paper(
    Q: np.ndarray,
    B: np.ndarray,
    alpha: float = 0.5,
    max_iter: int = 200,
    tol: float = 1e-10,
    x0: np.ndarray | None = None,
) -> SolveResult:
    """Damped, clipped Newton iteration ``x <- max(0, x - alpha Q^{-1}(Q x - b))`` for every column of ``B``.

    Q: (N, N) symmetric positive (semi-)definite float64; B: (N,) or (N, C). One Cholesky of Q serves every
    step and column; if Q is not numerically positive definite, ``Q^{-1}`` is ``(Q + j I)^{-1}`` with the
    smallest ``j = 1e-10 * 100^k * max(diag Q)`` that factorises (recorded in ``info["jitter"]``). Stops after
    ``max_iter`` steps or when ``max|x_{k+1} - x_k| <= tol * max|x_{k+1}|`` for every column. ``x0`` (N, C)
    defaults to 0. Returns a :class:`SolveResult` (method "paper") with the Gram-form objective
    ``x^T Q x - 2 b^T x`` and the relative KKT residual of the result, which is generally > 0.
    """
    if not 0.0 < alpha <= 1.0:
        raise ValueError("alpha must be in (0, 1]")
    t0 = time.perf_counter()
    Q = np.asarray(Q, dtype=np.float64)
    B2 = _as_2d(B)
    n, ncol = B2.shape
    X = np.zeros((n, ncol)) if x0 is None else np.maximum(_as_2d(x0).copy(), 0.0)
    converged = False
    iters = 0
    with single_blas_thread():
        fac = _Factor(Q, jitter0=1e-10)
        for iters in range(1, max_iter + 1):
            step = fac.solve(Q @ X - B2, refine=0)
            Xn = np.maximum(X - alpha * step, 0.0)
            change = np.max(np.abs(Xn - X), axis=0)
            size = np.max(np.abs(Xn), axis=0)
            X = Xn
            if np.all(change <= tol * np.where(size > 0, size, 1.0)):
                converged = True
                break
        kkt = kkt_residual(Q, B2, X)
        obj = objective(Q, B2, X)
    return SolveResult(
        x=X,
        iterations=iters,
        kkt_residual=kkt,
        objective=obj,
        seconds=time.perf_counter() - t0,
        method="paper",
        converged=converged,
        info={"alpha": alpha, "jitter": fac.jitter},
    )
