"""Stage ``evaluate``: compare every recovered envmap with the capture's truth (synthetic captures).

The true envmap is area-averaged (solid-angle exact) to the solve resolution and compared over the texels the
solve kept: relative RMSE, RMSE and SSIM of tonemapped maps, and the angle between brightest sources (see
objcam/metrics.py), each beside what the constant and the row-mean map of the truth score (objcam/baselines.py). A capture without ``truth/`` gets an explicit "no truth" record, not a silent pass.

Unknown albedo (the solve says so in solve.json) without pixels of known albedo (``scale_ambiguous`` true): the
envmap is known only up to one scale per colour channel, so it is compared after the best-fit scale per channel
(``scale_invariant`` None, the default), and so is the albedo image (solve's albedo.exr, over the pixels whose
albedo was estimated, albedo_mask.png). With pixels of known albedo the solve pins the scale (``scale_ambiguous``
false): envmap and albedo are compared as they are, and the albedo's fitted-scale figures are reported beside,
named ``*_fitted_scale`` (objcam.metrics.albedo_metrics).
The true albedo per pixel is rendered the way the transport stage renders a known albedo: the truth's textures and
values (truth/truth.json ``albedo``) put on the scene's meshes (the support plane's UVs re-made for the truth
texture's extent), the same camera and sub-pixel samples through Mitsuba, the mean albedo of the samples that hit.

Writes ``metrics.json`` ({target: metrics}), ``<target>/compare.png`` (truth | estimate | |error|, one
exposure: the scores' white, objcam.metrics.tonemap_scale, gamma 2.2) and ``<target>/overview.png`` (target
photo | truth | estimate, with titles).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.envmap import read_latlong, read_latlong_mask, resample_to_height, to_file
from objcam.figures import overview_figure
from objcam.errors import InputError
from objcam.image_io import atomic_write_text, read_exr, tonemap, write_png
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.artifacts import SceneArtifact
from objcam.truth import truth_albedo_image, truth_envmap_path

NAME = "evaluate"
DEPS = ("scene", "transport", "solve")
OPTIONAL_DEPS = ("probe",)  # chrome-ball ground truth: used where the capture has no truth/ envmap
VERSION = "3"
CODE_DEPS = ("objcam.metrics", "objcam.baselines", "objcam.truth")


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scale_invariant: bool | None = Field(None, description="fit the best global scale before comparing; None: a "
                                         "scale per colour channel where the albedo was unknown, one global scale "
                                         "for targets of relative radiometry (photos: an unknown camera gain), "
                                         "none elsewhere")


def input_files(capture: Path) -> list[Path]:
    truth = Path(capture) / "truth"
    if not truth.is_dir():
        return []
    return sorted(p for p in truth.rglob("*") if p.is_file() and p.suffix in (".exr", ".json"))


def _compare_png(path: Path, truth: np.ndarray, est: np.ndarray, mask: np.ndarray) -> None:
    """truth | estimate | |error|, each (H, 2H) of objcam's grid drawn in the standard file convention."""
    from objcam.metrics import tonemap_scale

    truth, est, mask = to_file(truth), to_file(est), to_file(mask)
    t, ref = tonemap(truth, tonemap_scale(truth, mask))  # the scores' white
    e, _ = tonemap(est, ref)
    err, _ = tonemap(np.abs(est - truth), ref)
    grey = np.where(mask[..., None], 1.0, 0.25)  # dim texels the solve did not model
    gap = np.ones((truth.shape[0], 2, 3))
    write_png(path, np.concatenate([t, gap, e * grey, gap, err * grey], axis=1))


def _albedo_compare_png(path: Path, truth: np.ndarray, est: np.ndarray, mask: np.ndarray) -> None:
    m = mask[..., None]
    gap = np.ones((truth.shape[0], 2, 3))
    t, e = np.where(m, truth, 0), np.where(m, est, 0)
    write_png(path, np.concatenate([t, gap, e, gap, np.abs(e - t) * 4], axis=1).clip(0, 1) ** (1 / 2.2))


def _albedo_results(inputs: StageInputs, scene, solve_dir: Path, names: list[str],
                    scale_invariant: bool | None) -> dict[str, dict]:
    """Albedo metrics per target whose solve estimated an albedo; one truth render per camera group. As estimated
    where the solve pinned the scale (or ``scale_invariant`` is False), after the per-channel scale otherwise."""
    import cv2

    from objcam.metrics import albedo_metrics
    from objcam.transport import load_transport
    from objcam.transport.storage import read_index

    index = read_index(inputs.upstream["transport"])
    truths: dict[str, np.ndarray | None] = {}
    out = {}
    for name in names:
        d = solve_dir / name
        if not (d / "albedo.exr").is_file():
            continue
        group = index["targets"][name]
        if group not in truths:
            tr = load_transport(inputs.upstream["transport"], name, load_A=False)
            truths[group] = truth_albedo_image(inputs.capture, scene.folder, tr)
        truth = truths[group]
        if truth is None:
            continue
        est = read_exr(d / "albedo.exr")[..., :3].astype(np.float64)
        mask = cv2.imread(str(d / "albedo_mask.png"), cv2.IMREAD_UNCHANGED) > 127
        if not mask.any():
            continue
        sinfo = json.loads((d / "solve.json").read_text())
        # pixels of known albedo pin the scale (scale_ambiguous false): score the albedo as it is; the fitted-scale
        # figures are reported beside it, named as such
        pinned = not bool(sinfo.get("scale_ambiguous", True)) if scale_invariant is None else not scale_invariant
        out[name] = albedo_metrics(est, truth, mask, pinned=pinned)
        _albedo_compare_png(inputs.out / name / "albedo_compare.png", truth, est * out[name]["albedo_scale"], mask)
    return out


def _probe_truth(inputs: StageInputs, target, height: int):
    """(envmap (H, 2H, 3), valid (H, 2H)) from the probe stage for the target's illumination, or None."""
    if "probe" not in inputs.upstream:
        return None
    from objcam.probe.truth import probe_truth

    return probe_truth(inputs.upstream["probe"], target.illumination or target.name, height)


def _finite_or_null(d: dict) -> dict:
    """``d`` with every non-finite float (nested dicts too) replaced by None."""
    return {k: _finite_or_null(v) if isinstance(v, dict) else
            (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in d.items()}


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    from objcam.baselines import with_baselines
    from objcam.metrics import envmap_metrics

    scene = SceneArtifact.load(inputs.upstream["scene"])
    solve_dir = inputs.upstream["solve"]
    results: dict[str, dict] = {}
    for target in scene.targets:
        tpath = truth_envmap_path(inputs.capture, target.name)
        est = read_latlong(solve_dir / target.name / "envmap.exr")[..., :3].astype(np.float64)
        mask = read_latlong_mask(solve_dir / target.name / "envmap_mask.png")
        sinfo = json.loads((solve_dir / target.name / "solve.json").read_text())
        unknown = sinfo.get("albedo") == "unknown" and bool(sinfo.get("scale_ambiguous", True))
        # unknown albedo (no pixel of known albedo to pin it): the envmap is known up to a scale per channel;
        # photos: up to the camera's unknown gain
        inv = params.scale_invariant if params.scale_invariant is not None else (
            "channel" if unknown else target.radiometry == "relative")
        source = "truth"
        if tpath is None:
            probe = _probe_truth(inputs, target, est.shape[0])
            if probe is None:
                continue
            truth, probe_valid = probe
            mask = mask & probe_valid  # only texels the ball shows
            source = "probe"
            # the probe's radiance is in the photos' units, not the targets' exposure: compare up to scale
            inv = inv or True
        else:
            truth_full = read_latlong(tpath)[..., :3].astype(np.float64)
            if not np.all(np.isfinite(truth_full)):
                raise InputError("truth envmap has NaN or infinite values", tpath, "re-export it")
            if truth_full.shape[1] != 2 * truth_full.shape[0]:
                raise InputError(f"truth envmap is {truth_full.shape[1]}x{truth_full.shape[0]}, not 2H x H",
                                 tpath)
            truth = resample_to_height(truth_full, est.shape[0])
        if not mask.any():
            continue
        # the constant and row-mean maps scored beside the estimate, and its skill over them (issue 28)
        m = with_baselines(envmap_metrics(est, truth, mask, scale_invariant=inv), truth, mask)
        # strict JSON: an undefined metric (e.g. no bright source in an all-zero estimate) is null, not NaN
        m = _finite_or_null(m)
        m["truth_source"] = source
        if sinfo.get("verdict"):  # the solve's own grade (issue 22), beside what the truth says of it
            m["verdict"] = {"grade": sinfo["verdict"]["grade"], "reasons": sinfo["verdict"]["reasons"]}
        m["truth_file"] = (str(tpath.relative_to(inputs.capture)) if tpath is not None
                           else f"objcam/probe/ ({target.illumination or target.name})")
        results[target.name] = m
        est = est * np.asarray(m.get("scale_channels", m["scale"]))  # the figures show what was compared
        _compare_png(inputs.out / target.name / "compare.png", truth, est, mask)
        overview_figure(inputs.out / target.name / "overview.png",
                        read_exr(solve_dir / target.name / "target.exr")[..., :3], truth, est, mask,
                        title=f"{target.name}: SSIM {m['ssim']:.3f}, relative RMSE {m['relative_rmse']:.3f}")

    for name, am in _albedo_results(inputs, scene, solve_dir, list(results), params.scale_invariant).items():
        results[name].update(am)
    if not results:
        atomic_write_text(inputs.out / "metrics.json", json.dumps({"truth": False}, indent=2))
        return StageOutputs(metrics={"truth": False}, summary="no truth/ in the capture: nothing to compare")
    atomic_write_text(inputs.out / "metrics.json", json.dumps(results, indent=2))
    keys = ("relative_rmse", "tonemapped_rmse", "ssim", "brightest_angle_deg", "albedo_relative_rmse",
            "albedo_ssim")
    mean = {k: float(np.mean([r[k] for r in results.values() if r.get(k) is not None])) for k in keys
            if any(r.get(k) is not None for r in results.values())}
    summary = ", ".join(f"{k} {v:.3f}" for k, v in mean.items()) + f" (mean of {len(results)} target(s))"
    rm = [r["baselines"]["row_mean"]["ssim"] for r in results.values() if "baselines" in r]
    if rm:
        beat = sum(r["beats_row_mean"]["ssim"] for r in results.values() if "baselines" in r)
        summary += f"; the truth's row-mean map scores SSIM {np.mean(rm):.3f} (beaten on {beat}/{len(rm)})"
    grades = [r["verdict"]["grade"] for r in results.values() if "verdict" in r]
    if grades:
        from objcam.solvers.plan.verdict import GRADES

        summary += "; verdict " + ", ".join(f"{grades.count(g)} {g}" for g in GRADES if g in grades)
    return StageOutputs(metrics={"targets": results, "mean": mean}, summary=summary)
