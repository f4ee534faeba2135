"""One call from (A, Y) to the envmap: form Q once, solve every column of Y."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from objcam.envmap import EnvGrid
from objcam.solvers.nnls import SolveResult, objective, solve_exact
from objcam.solvers.paper import solve_paper
from objcam.solvers.regularization import (
    DEFAULT_LR_REL,
    DEFAULT_LS_REL,
    absolute_weights,
    data_scale,
    difference_operator,
    gram,
    regularized_gram,
    rhs,
)


@dataclass
class GramSystem:
    """Q (N, N), B (N, C), yTy (C,) = ||y||^2 per column, and the regularisation weights used."""

    Q: np.ndarray
    B: np.ndarray
    yTy: np.ndarray
    ls_rel: float
    lr_rel: float
    ls_abs: float
    lr_abs: float
    data_scale: float
    seconds: float


def build_system(
    A: np.ndarray,
    Y: np.ndarray,
    grid: EnvGrid,
    texel_index: np.ndarray,
    ls: float = DEFAULT_LS_REL,
    lr: float = DEFAULT_LR_REL,
    relative: bool = True,
) -> GramSystem:
    """Form ``Q = A^T A + ls D^T D + lr I``, ``B = A^T Y`` and ``||y||^2`` per column.

    A: (M, N) float32/64 light transport (pixels x kept texels); Y: (M,) or (M, C) pixel values;
    texel_index: (N,) flat indices of the kept texels on ``grid``. With ``relative=True`` (default) ``ls`` and
    ``lr`` are multiples of ``s = mean(diag(A^T A))`` (see :mod:`objcam.solvers.regularization`); with
    ``relative=False`` they are used as given. Both forms are recorded in the result.
    """
    t0 = time.perf_counter()
    Y2 = np.asarray(Y)
    Y2 = Y2[:, None] if Y2.ndim == 1 else Y2
    if A.shape[1] != np.asarray(texel_index).size:
        raise ValueError(f"A has {A.shape[1]} columns but texel_index has {np.asarray(texel_index).size} texels")
    G = gram(A)
    s = data_scale(G)
    if relative:
        ls_abs, lr_abs = absolute_weights(G, ls, lr)
        ls_rel, lr_rel = float(ls), float(lr)
    else:
        ls_abs, lr_abs = float(ls), float(lr)
        ls_rel, lr_rel = (ls_abs / s, lr_abs / s) if s > 0 else (float("nan"), float("nan"))
    D = difference_operator(grid, texel_index)
    Q = regularized_gram(G, D, ls_abs, lr_abs)
    B = rhs(A, Y2)
    yTy = np.einsum("mc,mc->c", Y2.astype(np.float64), Y2.astype(np.float64))
    return GramSystem(Q, B, yTy, ls_rel, lr_rel, ls_abs, lr_abs, s, time.perf_counter() - t0)


def solve_envmap(
    A: np.ndarray,
    Y: np.ndarray,
    grid: EnvGrid,
    texel_index: np.ndarray,
    ls: float = DEFAULT_LS_REL,
    lr: float = DEFAULT_LR_REL,
    method: str = "exact",
    relative: bool = True,
    **solver_kwargs,
) -> SolveResult:
    """Solve ``min ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2, x >= 0`` for every column y of ``Y``.

    A: (M, N) pixels x kept texels; Y: (M,) or (M, C) (e.g. C = 3 colour channels); grid / texel_index as in
    :func:`build_system`; ``ls``, ``lr`` relative to mean(diag(A^T A)) unless ``relative=False``; defaults
    ``DEFAULT_LS_REL = 1e-2``, ``DEFAULT_LR_REL = 1e-4``. ``method``: "exact" (:func:`solve_exact`) or "paper"
    (:func:`solve_paper`); extra keyword arguments go to the solver.

    Returns a :class:`SolveResult` with x (N, C) radiance per kept texel, the full objective
    ``||A x - y||^2 + ls ||D x||^2 + lr ||x||^2`` per column, and in ``info`` the weights (ls_rel, lr_rel,
    ls_abs, lr_abs, data_scale) and the time spent forming Q (``form_seconds``; ``seconds`` is the solve only).
    """
    solvers = {"exact": solve_exact, "paper": solve_paper}
    if method not in solvers:
        raise ValueError(f"method must be one of {sorted(solvers)}, got {method!r}")
    sysm = build_system(A, Y, grid, texel_index, ls, lr, relative)
    res = solvers[method](sysm.Q, sysm.B, **solver_kwargs)
    res.objective = objective(sysm.Q, sysm.B, res.x, sysm.yTy)
    res.info.update(
        ls_rel=sysm.ls_rel,
        lr_rel=sysm.lr_rel,
        ls_abs=sysm.ls_abs,
        lr_abs=sysm.lr_abs,
        data_scale=sysm.data_scale,
        form_seconds=sysm.seconds,
    )
    return res
