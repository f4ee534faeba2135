"""Unknown albedo: one joint problem (a component of cameras and illuminations, objcam.solvers.assemble) solved
for every camera's albedo and every illumination's envmap, ``y_l = diag(rho_p) A'_p x_l``.

The plan, in order (:func:`solve_unknown`):

1. :func:`camera_blocks`: per camera, the pixels usable in every target (silhouette pixels that mix the object
   with a support of unknown albedo left out: :func:`mixed_pixels`), its rho-free transport A', the targets Y,
   the starting albedo and the pixels held at a known albedo (they pin the scale);
2. :func:`joint_setup`: the joint solve's weights (ls from the noise as for a known albedo, relative to
   A = diag(rho0) A'), prior and stopping rule (objcam.solvers.jointauto.JointSetup);
3. :func:`objcam.solvers.plan.bounce.solve_with_refits`: the joint solve (objcam.solvers.joint), stopped early
   and on a pixel subsample when a bounce refit follows; the support's light on the object redone from the
   estimated albedo and the joint solve rerun;
4. :func:`objcam.solvers.plan.final.final_step` (``final_envmap=known``): the albedo's total-variation step and
   every envmap at that albedo by the known-albedo solver (the texels the data barely see held to
   ``weak_texels``, as for a known albedo);
5. :func:`unknown_solutions`: each target's envmap, albedo, prediction and solve.json.

With one illumination and no pixel of known albedo the albedo alone explains every photo: the envmap then comes
from the priors, and solve.json says so (``envmap_constrained_by_data``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from objcam.envmap import EnvGrid
from objcam.errors import StageError
from objcam.solvers.assemble import grey_rho_free
from objcam.solvers.basis import texel_basis
from objcam.solvers.jointauto import JointSetup
from objcam.solvers.joint.groups import values_of
from objcam.solvers.plan.bounce import solve_with_refits
from objcam.solvers.plan.defaults import (
    EDGE_EPS_JOINT,
    JOINT_EDGE_STEPS,
    JOINT_LS0_REL,
    JOINT_TOL,
    JOINT_TOL_FINAL,
    JOINT_TOL_FINAL_ONE_ILLUMINATION,
    LP_ONE_ILLUMINATION,
    SCALE_NOTE,
    SCALE_PINNED_NOTE,
)
from objcam.solvers.plan.final import final_step
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.rules import basis_info, discrepancy_sigma, noise_ls, texel_group
from objcam.solvers.plan.targets import TargetData, TargetSolution, texel_mask


@dataclass
class PlanRecord:
    """What the plan records beside the joint result, for every target's solve.json."""

    solve_seconds: float
    conv: float  #: weights relative to A = diag(rho0) A' -> relative to A' (joint_setup)
    ls_source: str
    auto: dict | None  #: the auto_reg record, when a rule chose ls
    refits: list[dict]  #: one entry per bounce refit and camera
    final: dict | None  #: the final step's record
    unconstrained: bool  #: one illumination, every albedo unknown: the envmap comes from the priors
    solved: np.ndarray | None = None  #: (N_union,) bool the final step's solved texels (weak ones excluded)


def solve_unknown(scene, data: dict[str, TargetData], params: SolveParams, comp, tr_of_cam: dict,
                  names_of: dict) -> dict[str, TargetSolution]:
    """One joint problem: ``comp`` (objcam.solvers.assemble.components, with ``texel_index`` the union of its
    cameras' kept texels), ``tr_of_cam`` {camera: Transport}, ``names_of`` {(camera, illumination): target}."""
    grid = EnvGrid(tr_of_cam[comp.cameras[0]].env_height)
    cams = camera_blocks(scene, data, params, comp, tr_of_cam, names_of)
    L = len(comp.illuminations)
    # one illumination and no pixel of known albedo: every pixel's albedo can explain its value alone, so the data
    # do not constrain the envmap (its shape then comes from the priors; measured: image residual 0.000, SSIM 0.13
    # on the e2e bench's unknown-albedo capture against 0.47 with the albedo given); the bounce refit still runs
    # (objcam.solvers.plan.bounce: the export's render must match the prediction)
    # (a surface declared "uniform" constrains it: one albedo over the object's varied normals leaves its shading)
    unconstrained = L == 1 and all(bool(c["tr"].unknown_albedo[c["rows"]].all()) and c.get("groups") is None
                                   for c in cams)
    # the albedo's TV step and the envmaps at that albedo follow the joint solve (objcam.solvers.plan.final)
    with_final = (params.final_envmap == "known" and params.method == "exact" and params.prior == "edges"
                  and not unconstrained)
    setup, conv, ls_source, sigma = joint_setup(scene, data, params, cams, L, with_final)
    t0 = time.perf_counter()
    res, auto, refits = solve_with_refits(cams, comp, grid, setup, params, sigma)
    final_info, solved = None, None
    if with_final and not res.diverged:
        # the albedo's edge-preserving step and each envmap once more by the known-albedo solver
        t1 = time.perf_counter()
        # a weight chosen by auto_reg carries over; else the known-albedo rule's (from the noise)
        ls_rule = float(res.info["ls_rel"]) / conv if auto is not None else None
        X_final, rho_final, final_info = final_step(scene, data, cams, res, grid, comp.texel_index, params,
                                                    ls_rule, tv=setup.lp == 0)
        final_info["seconds"] = round(time.perf_counter() - t1, 3)
        solved = final_info.pop("solved", None)
        res = dataclasses.replace(res, x=X_final, rho=rho_final)
    solve_s = time.perf_counter() - t0
    # a diverging iteration (only the paper's damped steps can: the exact alternation is monotone) is stopped by
    # the solver, which returns the best estimate it saw: that is what is written, marked diverged, and the stage
    # summary says so in one line
    record = PlanRecord(round(solve_s, 4), conv, ls_source, auto, refits, final_info, unconstrained, solved)
    return unknown_solutions(params, comp, grid, cams, res, record)


def mixed_pixels(tr) -> np.ndarray:
    """(M,) bool: pixels whose sub-pixel samples see both the object and the support while some of the pixel's
    albedo is unknown. The joint model ``y = rho A' x`` gives a pixel one albedo; such a pixel is
    ``rho_obj A'_obj x + rho_sup A'_sup x``, whose ratio to A' x changes with the illumination, so no albedo fits
    it and what it cannot fit goes into the envmap (on the bench's dots scene its 163 silhouette pixels, 1% of
    the image, had a model error of 4% against 1.4% on the object)."""
    of = np.asarray(tr.object_fraction)
    return (of > 0) & (of < 1) & np.asarray(tr.unknown_albedo, bool)


#: objcam.solvers.joint's group labels of the surfaces capture.toml declares "uniform"
GROUP_OF = {"object": 1, "support": 2}


def uniform_groups(desc, tr, rows: np.ndarray) -> np.ndarray | None:
    """(M,) int group labels of the rows ``rows`` of the Transport ``tr`` (objcam.solvers.joint.groups): the
    pixels wholly on a surface whose albedo ``desc`` (SceneDescription) declares uniform and unknown share one
    albedo (GROUP_OF); 0 elsewhere. None when no surface is declared uniform."""
    of = np.asarray(tr.object_fraction)[rows]
    unknown = np.asarray(tr.unknown_albedo, bool)[rows]
    out = np.zeros(rows.size, np.int64)
    for which, on in (("object", of >= 1.0), ("support", of <= 0.0)):
        if getattr(desc, f"albedo_{which}").uniform:
            out[on & unknown] = GROUP_OF[which]
    return out if out.any() else None


def camera_blocks(scene, data: dict[str, TargetData], params: SolveParams, comp, tr_of_cam: dict,
                  names_of: dict) -> list[dict]:
    """Per camera of the problem, a dict: key, tr (Transport), rows (M,) its usable rows, A (M, N) float32 its
    rho-free transport over ``comp.texel_index``, Y (M, L, 3) the targets, rho0 (M, 3) the starting albedo,
    fixed (M,) bool the pixels held at a known albedo, targets (L names), sigma (the discrepancy rule's noise per
    target, or None), n_mixed (silhouette pixels left out), groups ((M,) int: the pixels of a surface of one
    unknown albedo, :func:`uniform_groups`, or None)."""
    cams = []
    for cam in comp.cameras:
        tr = tr_of_cam[cam]
        tnames = [names_of[(cam, ill)] for ill in comp.illuminations]
        use = np.logical_and.reduce([data[t].use for t in tnames])
        mixed = mixed_pixels(tr) if params.method == "exact" and params.mixed_pixels == "exclude" else None
        n_mixed = int((use & mixed).sum()) if mixed is not None else 0
        if mixed is not None:
            use = use & ~mixed
        if not use.any():
            raise StageError(f"no pixel is usable in every target of the camera of {tnames[0]!r} "
                             f"({', '.join(tnames)})", scene.folder / scene.target(tnames[0]).image,
                             "check the valid masks and saturation levels of these targets")
        rows = np.flatnonzero(use)
        A = grey_rho_free(tr, rows, comp.texel_index)
        Y = np.stack([data[t].y[rows] for t in tnames], axis=1)  # (M, L, 3)
        # start known pixels at their known albedo and unknown ones mid-range
        rho0 = np.where(tr.unknown_albedo[rows, None], 0.5, np.clip(tr.albedo[rows], 1e-3, 1.0))
        # pixels of known albedo (the object's, given in capture.toml) are held at it: they pin the scale that
        # unknown albedo alone leaves free (measured on the bench's dots scene: envmap SSIM 0.46 -> 0.51,
        # absolute albedo error 19% -> 1.5%). The paper's damped steps estimate every pixel's albedo, as the
        # method does: held pixels made them diverge there (objective x10 by sweep 8, no scale step to follow)
        fixed = ~tr.unknown_albedo[rows] if params.method == "exact" else np.zeros(rows.size, bool)
        groups = uniform_groups(scene.description, tr, rows) if params.method == "exact" else None
        sig = [discrepancy_sigma(scene.target(t), data[t].y[rows], params.auto_reg) for t in tnames]
        cams.append(dict(key=cam, tr=tr, rows=rows, A=A, Y=Y, rho0=rho0, fixed=fixed, targets=tnames, sigma=sig,
                         n_mixed=n_mixed, groups=groups))
    return cams


def joint_setup(scene, data: dict[str, TargetData], params: SolveParams, cams: list[dict], L: int,
                with_final: bool):
    """The joint solve's settings for this problem. Returns (JointSetup, conv: the factor from weights relative
    to A = diag(rho0) A' to weights relative to A', ls_source, sigma: the discrepancy rule's noises or None)."""
    lp = (0.0 if L >= 2 else LP_ONE_ILLUMINATION) if params.lp is None else params.lp
    final_tol = JOINT_TOL_FINAL if lp == 0 else JOINT_TOL_FINAL_ONE_ILLUMINATION
    tol = params.tol if params.tol is not None else (final_tol if with_final else JOINT_TOL)
    # the joint solve's weights are relative to A' (albedo 1); ls and lr are relative to A = diag(rho0) A', as for
    # a known albedo, so one number means one prior strength in both cases
    num = sum(float(np.sum((c["rho0"] ** 2).mean(axis=1) @ (c["A"].astype(np.float64) ** 2))) for c in cams)
    den = sum(float(np.sum(np.einsum("mn,mn->n", c["A"], c["A"], dtype=np.float64))) for c in cams)
    conv = num / den if den > 0 else 1.0
    # ls when not given and auto_reg is off: from the targets' noise, as for a known albedo (median over the
    # problem's targets); measured near the best envmap SSIM on the 3-illumination bench scene (bench/results.md)
    ls_source = "param"
    ls_fixed = params.ls
    if ls_fixed is None and params.auto_reg == "off":
        got = [noise_ls(scene.target(t), data[t].pooled, data[t].pooled_ok, params, c["tr"].downsample)
               for c in cams for t in c["targets"]]
        ls_fixed = float(np.median([g[0] for g in got]))
        ls_source = f"median over the targets of {got[0][1].split(' ')[0]} ls ({len(got)} targets)"
    setup = JointSetup(
        method=params.method, prior=params.prior if params.method == "exact" else "smooth",
        edge_eps=params.edge_eps if params.edge_eps is not None else EDGE_EPS_JOINT,
        edge_steps=min(params.edge_steps, JOINT_EDGE_STEPS),
        ls=None if params.auto_reg != "off" else ls_fixed * conv, lr=params.ridge * conv,
        lp=lp,
        rule=params.auto_reg, ls0=JOINT_LS0_REL, tol=tol, max_iter=params.max_iter,
        alpha=params.alpha, texel_group=texel_group(params, known=False), pinned_scale=params.pinned_scale)
    if with_final:  # its envmaps replace the joint solve's: no final exact x-step there
        setup = dataclasses.replace(setup, polish=False)
    sigma = [s for c in cams for s in c["sigma"] if s is not None] or None
    return setup, conv, ls_source, sigma


def unknown_solutions(params: SolveParams, comp, grid: EnvGrid, cams: list[dict], res,
                      record: PlanRecord) -> dict[str, TargetSolution]:
    """Each target's envmap, albedo (per camera), prediction and solve.json from the joint result ``res``
    (objcam.solvers.joint.JointResult, its envmaps possibly replaced by the final step's)."""
    L = len(comp.illuminations)

    # the texels the final step left out as weak (weak_texels=exclude) are not solved: 0 and unmarked
    mask = texel_mask(grid, comp.texel_index if record.solved is None else comp.texel_index[record.solved])
    n_held = int(sum(int(c["fixed"].sum()) for c in cams))  # pixels held at their known albedo
    # the surfaces of one unknown albedo: their value (at the solve's scale) and pixels
    gvals = values_of(res.rho, [c.get("groups") for c in cams])
    uniform = {name: [round(float(v), 5) for v in gvals[g]] for name, g in GROUP_OF.items() if g in gvals}
    n_uniform = int(sum(int((c["groups"] > 0).sum()) for c in cams if c.get("groups") is not None))
    per_target: dict[str, TargetSolution] = {}
    for p, c in enumerate(cams):
        tr, rows = c["tr"], c["rows"]
        rho = res.rho[p]  # (M_used, 3)
        hw = tr.image_shape[0] * tr.image_shape[1]
        alb = np.zeros((hw, 3), np.float32)
        alb[tr.pixel_index[rows]] = rho
        alb_mask = np.zeros(hw, bool)
        alb_mask[tr.pixel_index[rows][tr.unknown_albedo[rows]]] = True
        basis_rec = basis_info(comp.texel_index, texel_basis(grid, comp.texel_index, texel_group(params, False)),
                               params, known=False)
        for l, (ill, name) in enumerate(zip(comp.illuminations, c["targets"])):
            x = res.x[:, l, :]  # (N_union, 3)
            env = np.zeros((grid.n_texels, 3), np.float32)
            env[comp.texel_index] = x
            env = env.reshape(grid.height, grid.width, 3)
            fit = rho * (c["A"].astype(np.float64) @ x)  # (M_used, 3)
            pred = np.zeros((hw, 3), np.float32)
            pred[tr.pixel_index[rows]] = fit
            yv = c["Y"][:, l, :]
            rel_res = float(np.linalg.norm(fit - yv) / max(np.linalg.norm(yv), 1e-30))
            info = {
                "method": params.method, "albedo": "unknown", "scale_ambiguous": bool(res.scale_ambiguous),
                "note": SCALE_NOTE if res.scale_ambiguous else SCALE_PINNED_NOTE,
                "pixels_albedo_known": n_held,
                # the scale those pixels pin, chosen by their data alone (issue 29; objcam.solvers.joint.scale_step)
                "pinned_scale": res.info.get("pinned_scale"),
                "illumination": ill, "cameras_in_problem": len(cams), "illuminations_in_problem": L,
                "targets_in_problem": [t for cc in cams for t in cc["targets"]],
                "texels": int(comp.texel_index.size), **basis_rec,
                "pixels_used": int(rows.size),
                "pixels_excluded": int(tr.pixel_index.size - rows.size),
                "pixels_excluded_mixed": c["n_mixed"],
                "pixels_albedo_estimated": int(alb_mask.sum()),
                # declared "uniform" in capture.toml: one albedo per surface and colour (objcam.solvers.joint.groups)
                "albedo_uniform": uniform or None, "pixels_albedo_uniform": n_uniform,
                "solve_seconds": record.solve_seconds, "iterations": int(res.iterations),
                "converged": bool(res.converged), "message": res.message,
                "kkt_residual_max": (record.final["kkt_residual_max"] if record.final
                                     else float(np.max(res.kkt_x))),
                "kkt_residual_albedo_max": float(np.max(res.kkt_rho)),
                "objective": res.objective.tolist(), "objective_history": [float(v) for v in res.history],
                "objective_step_history": [float(v) for v in res.step_history],
                "relative_image_residual": rel_res,
                "ls_relative": float(res.info["ls_rel"]) / record.conv,
                "lr_relative": float(res.info["lr_rel"]) / record.conv,
                "ls_source": record.ls_source if record.auto is None else f"auto_reg {params.auto_reg}",
                "ls_relative_to_rho_free_A": float(res.info["ls_rel"]),
                "lp_relative": float(res.info["lp_rel"]), "scale_at_clip": [bool(v) for v in res.scale_at_clip],
                "auto_reg": record.auto, "prior": res.info["prior"], "diverged": bool(res.diverged),
                "envmap_constrained_by_data": not record.unconstrained, "bounce_refits": record.refits,
                "final_envmap": record.final,
                "objective_monotone": bool(np.all(np.diff(res.step_history) <= 1e-12 * np.abs(
                    np.asarray(res.step_history[:-1])))) if params.method == "exact" else None,
                "solver": {k: res.info[k] for k in (
                    "grams", "gram_seconds", "x_step_seconds", "gn_seconds", "scale_seconds", "rho_step_seconds",
                    "mm_steps", "edge_scale", "edge_eps", "edges_above_threshold", "anderson_accepted",
                    "gn_accepted") if k in res.info},
            }
            per_target[name] = TargetSolution(env, mask, pred.reshape(*tr.image_shape, 3), info,
                                              albedo=alb.reshape(*tr.image_shape, 3),
                                              albedo_mask=alb_mask.reshape(tr.image_shape))
    return per_target
