"""Stage ``evaluate``: compare every recovered envmap with the capture's truth (synthetic captures).

The true envmap is area-averaged (solid-angle exact) to the solve resolution and compared over the texels the
solve kept: relative RMSE, RMSE and SSIM of tonemapped maps, and the angle between brightest sources (see
objcam/metrics.py). A capture without ``truth/`` gets an explicit "no truth" record, not a silent pass.

Writes ``metrics.json`` ({target: metrics}), ``<target>/compare.png`` (truth | estimate | |error|, one
exposure: the truth's 99th percentile, gamma 2.2) and ``<target>/overview.png`` (target photo | truth |
estimate, with titles).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.envmap import resample_to_height
from objcam.figures import overview_figure
from objcam.errors import InputError
from objcam.image_io import atomic_write_text, read_exr, tonemap, write_png
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.artifacts import SceneArtifact

NAME = "evaluate"
DEPS = ("scene", "solve")
VERSION = "1"
CODE_DEPS = ("objcam.metrics",)


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scale_invariant: bool = Field(False, description="fit the best global scale before comparing (unknown albedo)")


def truth_envmap_path(capture: Path, target: str) -> Path | None:
    """Where a synthetic capture keeps the true envmap of ``target`` (see data_layout.md, truth/)."""
    meta = capture / "truth" / "truth.json"
    if meta.is_file():
        info = json.loads(meta.read_text())
        rel = info.get("envmaps", {}).get(target)
        if rel:
            return capture / rel
    for cand in (capture / "truth" / target / "envmap.exr", capture / "truth" / "envmap.exr"):
        if cand.is_file():
            return cand
    return None


def input_files(capture: Path) -> list[Path]:
    truth = Path(capture) / "truth"
    if not truth.is_dir():
        return []
    return sorted(p for p in truth.rglob("*") if p.is_file() and p.suffix in (".exr", ".json"))


def _compare_png(path: Path, truth: np.ndarray, est: np.ndarray, mask: np.ndarray) -> None:
    t, ref = tonemap(truth)
    e, _ = tonemap(est, ref)
    err, _ = tonemap(np.abs(est - truth), ref)
    grey = np.where(mask[..., None], 1.0, 0.25)  # dim texels the solve did not model
    gap = np.ones((truth.shape[0], 2, 3))
    write_png(path, np.concatenate([t, gap, e * grey, gap, err * grey], axis=1))


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    import cv2

    from objcam.metrics import envmap_metrics

    scene = SceneArtifact.load(inputs.upstream["scene"])
    solve_dir = inputs.upstream["solve"]
    results: dict[str, dict] = {}
    for target in scene.targets:
        tpath = truth_envmap_path(inputs.capture, target.name)
        if tpath is None:
            continue
        est = read_exr(solve_dir / target.name / "envmap.exr")[..., :3].astype(np.float64)
        mask = cv2.imread(str(solve_dir / target.name / "envmap_mask.png"), cv2.IMREAD_UNCHANGED) > 127
        truth_full = read_exr(tpath)[..., :3].astype(np.float64)
        if truth_full.shape[1] != 2 * truth_full.shape[0]:
            raise InputError(f"truth envmap is {truth_full.shape[1]}x{truth_full.shape[0]}, not 2H x H", tpath)
        truth = resample_to_height(truth_full, est.shape[0])
        m = envmap_metrics(est, truth, mask, scale_invariant=params.scale_invariant)
        # strict JSON: an undefined metric (e.g. no bright source in an all-zero estimate) is null, not NaN
        m = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in m.items()}
        m["truth_file"] = str(tpath.relative_to(inputs.capture))
        results[target.name] = m
        _compare_png(inputs.out / target.name / "compare.png", truth, est, mask)
        overview_figure(inputs.out / target.name / "overview.png",
                        read_exr(solve_dir / target.name / "target.exr")[..., :3], truth, est, mask,
                        title=f"{target.name}: SSIM {m['ssim']:.3f}, relative RMSE {m['relative_rmse']:.3f}")

    if not results:
        atomic_write_text(inputs.out / "metrics.json", json.dumps({"truth": False}, indent=2))
        return StageOutputs(metrics={"truth": False}, summary="no truth/ in the capture: nothing to compare")
    atomic_write_text(inputs.out / "metrics.json", json.dumps(results, indent=2))
    keys = ("relative_rmse", "tonemapped_rmse", "ssim", "brightest_angle_deg")
    mean = {k: float(np.mean([r[k] for r in results.values() if r.get(k) is not None])) for k in keys
            if any(r.get(k) is not None for r in results.values())}
    summary = ", ".join(f"{k} {v:.3f}" for k, v in mean.items()) + f" (mean of {len(results)} target(s))"
    return StageOutputs(metrics={"targets": results, "mean": mean}, summary=summary)
