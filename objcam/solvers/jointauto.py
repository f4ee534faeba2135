"""The joint solve with its smoothness weight chosen automatically (what the solve stage runs with unknown albedo).

The criteria of :mod:`objcam.solvers.autoreg` need a problem that is linear in the envmap. For fixed albedo the
joint problem is exactly that: ``y_pl = diag(rho_p) A'_p x_l`` stacked over cameras p, one column per
illumination and channel. So:

1. a provisional joint solve at ``ls0`` (relative; loose tolerance: only its albedo is used);
2. the rule (GCV, discrepancy or L-curve) on ``A_eff = [diag(rho_p) A'_p]_p`` (rho: the provisional albedo,
   grey = channel mean) and all the illuminations' pixels as columns: ls for the envmap prior;
3. the final joint solve at that ls, started from the provisional albedo.

The albedo scale of step 1 is arbitrary (scale ambiguity), but both criteria and the relative weights are
invariant to it: scaling rho by c scales A_eff^T A_eff and its mean diagonal by c^2 alike. The weights are
converted between the two relative conventions (``mean diag(A_eff^T A_eff)`` there, ``mean diag(sum A'^T A')``
in :func:`objcam.solvers.solve_joint`), so the ls chosen is the one the criterion meant.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from objcam.envmap import EnvGrid
from objcam.solvers.autoreg import choose_weights
from objcam.solvers.basis import texel_basis
from objcam.solvers.joint import CameraBlock, JointResult, solve_joint


@dataclass
class JointSetup:
    """Weights and stopping rule of :func:`solve_joint_auto`.

    ls: relative smoothness, or None to choose it by ``rule`` ("gcv", "discrepancy", "lcurve"; "off" uses ls0).
    lr, lp: relative ridge and albedo weights (objcam.solvers.joint conventions). ls0: ls of the provisional
    solve. method: "exact" or "paper" (alpha: its envmap damping). prior: "edges" (Huber; edge_eps its threshold,
    edge_steps its majorise-minimise x-steps per sweep) or "smooth" (quadratic); the paper's method is always
    smooth. tol, max_iter: the final solve's stopping rule. polish: end on the exact float64 x-step
    (:func:`objcam.solvers.solve_joint`; off for a solve that only provides a starting point). texel_group: the
    envmap basis' group size (:func:`objcam.solvers.basis.texel_basis`; 0: one unknown per texel).
    pinned_scale: with pixels of known albedo, end on the scale their data alone choose (issue 29).
    """

    method: str = "exact"
    prior: str = "edges"
    edge_eps: float = 0.05
    edge_steps: int = 2
    ls: float | None = None
    lr: float = 1e-4
    lp: float = 0.0
    rule: str = "gcv"
    ls0: float = 1e-2
    tol: float = 1e-6
    max_iter: int = 100
    alpha: float = 0.5
    polish: bool = True
    texel_group: float = 0.0
    pinned_scale: bool = True


def solve_joint_auto(blocks: Sequence[CameraBlock | tuple], grid: EnvGrid, texel_index: np.ndarray,
                     setup: JointSetup, sigma: Sequence[float] | None = None
                     ) -> tuple[JointResult, dict[str, Any] | None]:
    """Run the joint solve with ``setup``'s weights (ls chosen by the rule when None); see the module docstring.

    blocks: as :func:`objcam.solvers.solve_joint` (A' (M_p, N), Y (M_p, L, C), pixel_index, image_shape, rho0).
    sigma: absolute noise standard deviations of one pixel value (the discrepancy rule uses their median).
    Returns the final :class:`JointResult` and a dict on the automatic choice (None when ls was given).
    """
    kw: dict[str, Any] = dict(lr=setup.lr, lp=setup.lp, method=setup.method, max_iter=setup.max_iter,
                              prior=setup.prior if setup.method == "exact" else "smooth", polish=setup.polish,
                              pinned_scale=setup.pinned_scale, basis=texel_basis(grid, texel_index, setup.texel_group))
    if setup.method == "paper":
        kw["alpha"] = setup.alpha
    else:
        kw.update(edge_eps=setup.edge_eps, edge_steps=setup.edge_steps)
    if setup.ls is not None or setup.rule == "off":
        ls = setup.ls if setup.ls is not None else setup.ls0
        return solve_joint(blocks, grid, texel_index, ls=ls, tol=setup.tol, **kw), None
    t0 = time.perf_counter()
    # only its albedo is used: the quadratic prior is enough (and cheaper)
    first = solve_joint(blocks, grid, texel_index, ls=setup.ls0, tol=max(setup.tol, 1e-3),
                        **{**kw, "prior": "smooth"})
    if first.diverged:
        return first, {"rule": setup.rule, "note": "the provisional solve diverged"}
    t_first = time.perf_counter() - t0
    blocks = [b if isinstance(b, CameraBlock) else CameraBlock(*b) for b in blocks]
    A_eff = np.concatenate([(r.mean(axis=1)[:, None] * np.asarray(b.A, np.float64)) for b, r in
                            zip(blocks, first.rho)])
    Y = np.concatenate([np.asarray(b.Y, np.float64).reshape(np.asarray(b.A).shape[0], -1) for b in blocks])
    s_joint = float(first.info["data_scale"])
    # lr is relative to mean(diag(sum A'^T A')) here, to mean(diag(A_eff^T A_eff)) in choose_weights
    s_eff = float(np.mean(np.einsum("mn,mn->n", A_eff, A_eff)))
    sig = float(np.median(sigma)) if (setup.rule == "discrepancy" and sigma) else None
    ls_e, _, info = choose_weights(A_eff, Y, grid, texel_index, rule=setup.rule, sigma=sig,
                                   lr=setup.lr * s_joint / s_eff)
    ls = ls_e * s_eff / s_joint
    t_rule = time.perf_counter() - t0 - t_first
    # the final solve starts from the provisional albedo; the pixels of known albedo stay held
    blocks = [CameraBlock(b.A, b.Y, b.pixel_index, b.image_shape, r, b.fixed, b.groups)
              for b, r in zip(blocks, first.rho)]
    res = solve_joint(blocks, grid, texel_index, ls=ls, tol=setup.tol, **kw)
    auto = {"rule": setup.rule, "ls_relative": float(ls), "ls0_relative": setup.ls0,
            "provisional_seconds": round(t_first, 3), "criterion_seconds": round(t_rule, 3),
            "final_seconds": round(res.seconds, 3), "notes": list(info["notes"])}
    return res, auto
