"""Envmap solvers: ``min ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2, x >= 0`` in Gram form.

- :mod:`.regularization`: the difference operator D, the Gram matrix, the relative weight scaling.
- :mod:`.nnls`: :func:`solve_exact` (block principal pivoting, exact to a relative KKT residual ~1e-10).
- :mod:`.paper`: :func:`solve_paper`, the paper's damped clipped Newton iteration (baseline).
- :mod:`.problem`: :func:`solve_envmap`, from (A, Y) to x in one call.
- :mod:`.basis`: the merged envmap basis (texels of a lat-long row joined near the poles) the solve stage uses.
- :mod:`.joint`: :func:`solve_joint`, the albedo and the envmaps together when the albedo is unknown.
"""

from objcam.solvers.autoreg import choose_weights
from objcam.solvers.joint import JointResult, solve_joint
from objcam.solvers.nnls import SolveResult, kkt_residual, objective, solve_exact
from objcam.solvers.paper import solve_paper
from objcam.solvers.problem import GramSystem, build_system, solve_envmap
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

__all__ = [
    "JointResult",
    "choose_weights",
    "solve_joint",
    "DEFAULT_LR_REL",
    "DEFAULT_LS_REL",
    "GramSystem",
    "SolveResult",
    "absolute_weights",
    "build_system",
    "data_scale",
    "difference_operator",
    "gram",
    "kkt_residual",
    "objective",
    "regularized_gram",
    "rhs",
    "solve_envmap",
    "solve_exact",
    "solve_paper",
]
