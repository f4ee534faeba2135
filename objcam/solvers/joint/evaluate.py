"""Evaluating a joint estimate: its objective (:func:`joint_objective`), its envmaps as images
(:func:`scatter_envmaps`) and its errors against a known truth after the best-fit scale (:func:`evaluate_joint`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from objcam.envmap import EnvGrid
from objcam.metrics import relative_rmse
from objcam.solvers.joint.blocks import DEFAULT_RHO_MIN, CameraBlock
from objcam.solvers.joint.problem import JointProblem
from objcam.solvers.regularization import DEFAULT_LR_REL, DEFAULT_LS_REL
from objcam.threads import single_blas_thread


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
    """The objective per channel (C,) of :func:`objcam.solvers.joint.solve_joint` at (x (N, L, C), rho list of
    (M_p, C)).

    prior="edges" needs the Huber scale per target that the solve fixed (``JointResult.info["edge_scale"]``); the
    shared edge term is split equally between the channels (as ``JointResult.objective``)."""
    J = JointProblem(blocks, grid, texel_index, ls, lr, lp, relative, DEFAULT_RHO_MIN, prior=prior,
                     edge_eps=edge_eps)
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
    """The least-squares k of ``k est ~ truth`` (1 for a zero estimate)."""
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
