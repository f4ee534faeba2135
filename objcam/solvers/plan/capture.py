"""The solve of a whole capture: its targets split into independent problems, each solved by its plan.

:func:`solve_capture` is the solve stage's one entry point. Targets are grouped by objcam.solvers.assemble
(targets of one camera share its albedo, targets with one ``illumination`` name share an envmap); a problem whose
pixels all have a known albedo is solved target by target (:mod:`objcam.solvers.plan.known`), one with unknown
albedo jointly (:mod:`objcam.solvers.plan.unknown`). ``method=adam`` sends every target to the
gradient-descent baseline through Mitsuba (objcam.solvers.adam) instead.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from objcam.envmap import EnvGrid
from objcam.errors import StageError
from objcam.solvers.adam import AdamSettings, solve_adam_targets
from objcam.solvers.assemble import components
from objcam.solvers.plan.defaults import KNOWN_LS_REL
from objcam.solvers.plan.known import solve_known
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.targets import TargetData, TargetSolution, texel_mask
from objcam.solvers.plan.unknown import solve_unknown
from objcam.solvers.plan.verdict import assess
from objcam.threads import single_blas_thread


def solve_capture(scene, data: dict[str, TargetData], params: SolveParams,
                  capture: Path) -> dict[str, TargetSolution]:
    """Every target of ``scene`` (objcam.schemas.artifacts.SceneArtifact), in the scene's order.

    data: {target: TargetData} as the solve stage loads them; capture: the capture folder (for error messages).
    Raises StageError for what the capture asks that cannot be solved (a supersampled A with method=adam,
    inconsistent illumination names).
    """
    if params.method == "adam" and any(d.transport.output_height != d.transport.env_height for d in data.values()):
        # (an unknown albedo is refused by the transport stage, before it builds a supersampled A)
        raise StageError("a supersampled transport (transport.supersample) is solved by method exact or paper, "
                         "not method=adam", capture / "capture.toml", "set transport.supersample=1")
    if params.method == "adam":
        return with_verdicts(scene, data, params, solve_adam(scene, data, params))
    pairs = [(str(data[t.name].transport.folder), getattr(t, "illumination", "") or t.name, t.name)
             for t in scene.targets]
    try:
        comps = components(pairs)
    except ValueError as e:
        raise StageError(str(e), capture / "capture.toml",
                         "fix the targets' illumination names in capture.toml") from None
    tr_of_cam = {cam: data[t].transport for cam, _, t in pairs}
    names_of = {(cam, ill): t for cam, ill, t in pairs}
    per_target: dict[str, TargetSolution] = {}
    for comp in comps:
        unknown = any(tr_of_cam[c].unknown_albedo.any() for c in comp.cameras)
        names = [names_of[(c, i)] for c in comp.cameras for i in comp.illuminations]
        if not unknown:
            per_target.update(solve_known(scene, data, params, names))
            continue
        comp.texel_index = np.unique(np.concatenate([tr_of_cam[c].texel_index for c in comp.cameras]))
        per_target.update(solve_unknown(scene, data, params, comp, tr_of_cam, names_of))
    return with_verdicts(scene, data, params, {t.name: per_target[t.name] for t in scene.targets})


def with_verdicts(scene, data: dict[str, TargetData], params: SolveParams,
                  sols: dict[str, TargetSolution]) -> dict[str, TargetSolution]:
    """Every solution's solve.json gains ``verdict`` (objcam.solvers.plan.verdict: grade, reasons, measures)."""
    for name, sol in sols.items():
        t0 = time.perf_counter()
        with single_blas_thread():
            v = assess(scene.target(name), data[name], sol, params.ridge, full=params.verdict == "full")
        v["seconds"] = round(time.perf_counter() - t0, 4)
        sol.info["verdict"] = v
    return sols


def solve_adam(scene, data: dict[str, TargetData], params: SolveParams) -> dict[str, TargetSolution]:
    """method=adam: every target through objcam.solvers.adam (per camera group with unknown albedo)."""
    settings = AdamSettings(lr=params.adam_lr, seconds=params.adam_seconds, max_iter=params.adam_max_iter,
                            spp=params.adam_spp, ls=params.ls if params.ls is not None else KNOWN_LS_REL,
                            lr_ridge=params.ridge, lp=0.0 if params.lp is None else params.lp,
                            converge_tol=params.adam_converge_tol, patience=params.adam_patience,
                            stop_on_plateau=params.adam_stop_on_plateau)
    out: dict[str, TargetSolution] = {}
    for name, r in solve_adam_targets(scene, data, settings).items():
        tr = data[name].transport
        grid = EnvGrid(tr.env_height)
        out[name] = TargetSolution(r.envmap, texel_mask(grid, tr.texel_index), r.prediction, r.info,
                                   albedo=r.albedo, albedo_mask=r.albedo_mask)
    return out
