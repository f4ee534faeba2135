"""Stage ``solve``: recover each target's environment map from its transport matrix A (and, where the capture
leaves it unknown, the albedo).

The stage reads the scene and transport artifacts, pools every target photo to A's pixels, hands them to the
solve's plan (:func:`objcam.solvers.plan.capture.solve_capture`: known albedo target by target, unknown albedo
as joint problems, or the Adam baseline; every setting in :class:`objcam.solvers.plan.params.SolveParams`) and
writes what it returns.

Writes per target ``<target>/``: envmap.exr (full lat-long, 0 where unsolved), envmap_mask.png (255 = solved
texel), prediction.exr, residual.exr (target - prediction, 0 at unused pixels), outliers.png (255 = a pixel
dropped as an outlier, when any were), target.exr (the pooled target that was fitted), tonemapped PNGs of each,
and solve.json; with unknown albedo also albedo.exr (pooled image size, 0 where not estimated), albedo.png and
albedo_mask.png (255 where the albedo was unknown and estimated); with a supersampled A
(``transport.supersample``) also envmap_fine.exr and envmap_fine_mask.png on A's grid, envmap.exr being their
area average. Lat-long files (envmap*.exr, envmap*.png) are in the standard file convention
(objcam.envmap.to_file).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from objcam.errors import StageError
from objcam.envmap import write_latlong, write_latlong_png
from objcam.image_io import atomic_write_text, tonemap, write_exr, write_png, write_tonemapped_png
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.artifacts import SceneArtifact
from objcam.solvers.plan.capture import solve_capture
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.summary import solve_summary
from objcam.solvers.plan.targets import TargetData, TargetSolution
from objcam.transport import load_transport
from objcam.transport.pixels import target_rows
from objcam.transport.storage import read_index

NAME = "solve"
DEPS = ("scene", "transport")
VERSION = "5"
CODE_DEPS = ("objcam.solvers", "objcam.transport")

Params = SolveParams


def run(inputs: StageInputs, params: SolveParams) -> StageOutputs:
    scene = SceneArtifact.load(inputs.upstream["scene"])
    t_all = time.perf_counter()
    data = load_targets(scene, inputs.upstream["transport"])
    solutions = solve_capture(scene, data, params, inputs.capture)
    if params.align == "auto":
        data, solutions = aligned(scene, data, solutions, params, inputs.capture)
    for name, sol in solutions.items():
        write_target(inputs.out / name, sol, data[name])
    summary, metrics = solve_summary({k: s.info for k, s in solutions.items()}, params.method,
                                     time.perf_counter() - t_all)
    return StageOutputs(metrics=metrics, summary=summary)


def load_targets(scene, transport_dir: Path) -> dict[str, TargetData]:
    """Per target of ``scene`` its pooled photo at A's rows; one Transport per camera group."""
    index = read_index(transport_dir)
    by_group: dict[str, object] = {}
    out = {}
    for target in scene.targets:
        g = index["targets"].get(target.name)
        if g not in by_group:
            by_group[g] = load_transport(transport_dir, target.name)
        tr = by_group[g]
        pooled, ok, y, use = target_rows(target.load_image(scene.folder), target.load_valid(scene.folder),
                                         tr.downsample, tr.pixel_index)
        if not use.any():
            raise StageError("no usable pixel sees the scene", scene.folder / target.image,
                             "check the camera pose and the valid mask")
        out[target.name] = TargetData(tr, pooled, ok, y, use)
    return out


def aligned(scene, data: dict[str, TargetData], solutions: dict[str, TargetSolution], params: SolveParams,
            capture: Path) -> tuple[dict[str, TargetData], dict[str, TargetSolution]]:
    """``data`` and ``solutions`` after registering each camera's photos to the model (objcam.solvers.plan.align):
    per round one shift per camera from its targets' predictions, the photos resampled where it is significant and
    the capture solved again. Every solution's info gets ``alignment``: the total shift in the photo's pixels and
    each round's estimate (pixels of A's grid)."""
    from objcam.solvers.plan.align import MIN_GAIN, ROUNDS, estimate_shift, fit_gain, shift_image, significant

    specs = {t.name: t for t in scene.targets}
    photos: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # full-resolution photo and valid mask, read once

    def photo(n: str) -> tuple[np.ndarray, np.ndarray]:
        if n not in photos:
            photos[n] = specs[n].load_image(scene.folder), specs[n].load_valid(scene.folder)
        return photos[n]

    groups: dict[int, list[str]] = {}
    for name, d in data.items():
        groups.setdefault(id(d.transport), []).append(name)
    total = {g: np.zeros(2) for g in groups}
    rounds: dict[int, list[dict]] = {g: [] for g in groups}
    active = list(groups)  # the cameras whose shift may still change: every one, then those moved last round
    for _ in range(ROUNDS):
        moved: list[int] = []
        before = (dict(data), solutions, {g: total[g].copy() for g in groups})
        for g in active:
            names = groups[g]
            tr = data[names[0]].transport
            kept = tr.kept_mask().reshape(-1)
            usable = []
            for n in names:
                u = data[n].pooled_ok.reshape(-1) & kept
                if solutions[n].rejected is not None:
                    u[tr.pixel_index[solutions[n].rejected]] = False
                usable.append(u.reshape(data[n].pooled_ok.shape))
            est = estimate_shift([solutions[n].prediction for n in names], [data[n].pooled for n in names], usable)
            take = significant(est)
            rounds[g].append({"shift": [round(float(v), 4) for v in est["shift"]],
                              "stderr": [round(float(v), 4) for v in est["stderr"]], "taken": take})
            if not take:
                continue
            moved.append(g)
            total[g] += est["shift"]
            for n in names:
                img, ok = shift_image(*photo(n), total[g] * tr.downsample)
                data[n] = TargetData(tr, *target_rows(img, ok, tr.downsample, tr.pixel_index))
        if not moved:
            break
        solutions = solve_capture(scene, data, params, capture)
        shifted = [n for g in moved for n in groups[g]]
        gain = fit_gain([_chi2(before[1][n]) for n in shifted], [_chi2(solutions[n]) for n in shifted])
        for g in moved:
            rounds[g][-1]["fit_gain"] = round(gain, 4)
        if not gain >= MIN_GAIN:  # the shift bought little: model error, not the pose; keep the round before
            data, solutions, total = before
            for g in moved:
                rounds[g][-1]["taken"] = False
            break
        active = moved
    for g, names in groups.items():
        f = data[names[0]].transport.downsample
        for n in names:
            solutions[n].info["alignment"] = {"shift_px": [round(float(v) * f, 4) for v in total[g]],
                                              "rounds": rounds[g]}
    return data, solutions


def _chi2(sol: TargetSolution) -> float:
    """A solution's misfit: the verdict's chi-squared per value, else its relative image residual squared."""
    v = (sol.info.get("verdict") or {}).get("chi2")
    return float(v) if v is not None else float(sol.info.get("relative_image_residual", 0.0)) ** 2


def write_target(d: Path, sol: TargetSolution, data: TargetData) -> None:
    """One target's artifacts (see the module docstring)."""
    resid = np.where(data.pooled_ok[..., None], data.pooled - sol.prediction, 0.0)
    if sol.fine is not None:
        write_latlong(d / "envmap_fine.exr", sol.fine[0])
        write_latlong_png(d / "envmap_fine_mask.png", sol.fine[1].astype(float))
    write_latlong(d / "envmap.exr", sol.envmap)
    write_latlong_png(d / "envmap_mask.png", sol.mask.astype(float))
    write_exr(d / "prediction.exr", sol.prediction)
    write_exr(d / "residual.exr", resid)
    write_exr(d / "target.exr", data.pooled)
    write_latlong_png(d / "envmap.png", tonemap(sol.envmap)[0])
    ref = write_tonemapped_png(d / "target.png", data.pooled)
    write_tonemapped_png(d / "prediction.png", sol.prediction, exposure_ref=ref)
    write_tonemapped_png(d / "residual.png", np.abs(resid), exposure_ref=ref)
    if sol.rejected is not None:  # the pixels the solve dropped as outliers (objcam.solvers.outliers)
        mask = np.zeros(data.pooled.shape[:2], bool)
        mask.ravel()[data.transport.pixel_index[sol.rejected]] = True
        write_png(d / "outliers.png", mask.astype(float))
    if sol.albedo is not None:
        write_exr(d / "albedo.exr", sol.albedo)
        write_png(d / "albedo.png", np.clip(sol.albedo, 0, 1) ** (1 / 2.2))  # albedo is in [0, 1]: no exposure
        write_png(d / "albedo_mask.png", sol.albedo_mask.astype(float))
    atomic_write_text(d / "solve.json", json.dumps(sol.info, indent=2))

