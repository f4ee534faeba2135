"""What the block steps of one joint solve share: the problem, the step settings, the timers and the caches.

The x-, rho- and scale steps (:mod:`.x_step`, :mod:`.rho_step`, :mod:`.scale_step`) are functions of a
:class:`StepContext` and the current point; the alternation (:mod:`.alternation`) owns the point.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from objcam.solvers.joint.problem import JointProblem


@dataclass
class PCGReference:
    """The reference Gram matrices that precondition the x-steps by PCG (``xsolver="pcg"``) and their counters."""

    grams: dict[int, np.ndarray] = field(default_factory=dict)  # channel c -> its data Gram (N, N) at some albedo
    stale: set[int] = field(default_factory=set)  # channels whose albedo moved away: new Gram at the next x-step
    applications: int = 0  # operator applications (each two passes over A') of every x-step by PCG
    rounds: int = 0  # pivoting rounds of every x-step by PCG
    refreshes: int = 0  # reference Gram matrices formed
    steps: int = 0  # x-steps by PCG


@dataclass
class StepContext:
    """The problem J and the settings of :func:`objcam.solvers.joint.solve_joint` that its block steps read.

    exact: exact block minimisation (else the paper's damped steps with ``alpha`` for x and ``beta`` for rho).
    qp_tol: tolerance of the exact x- and rho-subproblem solves. fast_gram: Gram matrices from float32 products.
    use_pcg: x-steps by PCG (:mod:`.pcg`) instead of formed Gram matrices, with a new reference Gram when a step
    needs more than ``cg_refresh`` operator applications per pivoting round.
    timers: seconds spent in the x-, rho-, subspace (gn) and scale steps. gram_cache: the Gram matrices of the
    current sweep, keyed by the albedo values (shared by the x-steps of one sweep).
    """

    J: JointProblem
    exact: bool
    alpha: float
    beta: float
    qp_tol: float
    fast_gram: bool
    use_pcg: bool
    cg_refresh: int
    timers: dict[str, float] = field(default_factory=lambda: dict(x=0.0, rho=0.0, gn=0.0, scale=0.0))
    pcg: PCGReference = field(default_factory=PCGReference)
    gram_cache: dict = field(default_factory=dict)
