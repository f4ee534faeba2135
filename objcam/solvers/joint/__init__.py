"""Joint recovery of the albedo and the environment maps (unknown albedo, several illuminations, several cameras).

Camera p sees M_p valid pixels with rho-free light transport ``A'_p`` (M_p, N) and per-pixel albedo ``rho_p``
(M_p, C); the photo of target (illumination) l in channel c is ``y_plc = diag(rho_pc) A'_p x_lc``. The solve
minimises, per colour channel, the data misfit plus an envmap prior (quadratic smoothness, or the edge-preserving
Huber prior) and an optional albedo smoothness prior, subject to ``x >= 0`` and ``rho_min <= rho <= 1``, by
alternating exact block steps with safeguarded accelerations. The albedo and radiance are known only up to a
scale per channel unless some pixels have a known albedo.

Modules, each documenting its part:

- :mod:`.blocks`: the inputs (:class:`CameraBlock`), the albedo regulariser G, the albedo defaults.
- :mod:`.problem`: the model, the envmap priors and the weights (:class:`~.problem.JointProblem`).
- :mod:`.kernels`: blocked float32/float64 products with A', :func:`weighted_gram`, the jittered Cholesky.
- :mod:`.albedo`, :mod:`.boxqp`: the per-pixel albedo least squares (:func:`albedo_at`), the sparse box QP.
- :mod:`.x_step` (with :mod:`.pcg`), :mod:`.rho_step`, :mod:`.scale_step`: the exact block steps.
- :mod:`.accelerate`: subspace Gauss-Newton and Anderson proposals.
- :mod:`.alternation`: the sweeps, the stopping rule, the divergence guard; :mod:`.context`: what the steps share.
- :mod:`.solve`: :func:`solve_joint` and :class:`JointResult`; :mod:`.evaluate`: objective and errors of an
  estimate.
"""

from objcam.solvers.joint.albedo import albedo_at
from objcam.solvers.joint.blocks import (
    DEFAULT_RHO0,
    DEFAULT_RHO_MIN,
    CameraBlock,
    NoValidPixelsError,
    albedo_smoothness_operator,
)
from objcam.solvers.joint.boxqp import BoxQPResult, box_kkt_residual, solve_box_qp
from objcam.solvers.joint.evaluate import evaluate_joint, joint_objective, scatter_envmaps
from objcam.solvers.joint.kernels import weighted_gram
from objcam.solvers.joint.solve import JointResult, solve_joint

__all__ = [
    "DEFAULT_RHO0",
    "DEFAULT_RHO_MIN",
    "BoxQPResult",
    "CameraBlock",
    "JointResult",
    "NoValidPixelsError",
    "albedo_at",
    "albedo_smoothness_operator",
    "box_kkt_residual",
    "evaluate_joint",
    "joint_objective",
    "scatter_envmaps",
    "solve_box_qp",
    "solve_joint",
    "weighted_gram",
]
