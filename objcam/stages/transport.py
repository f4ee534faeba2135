"""Stage ``transport``: the light-transport matrix A (y = A x) of every distinct target camera.

Reads the scene artifact (scene.json, meshes, targets.json); writes one zarr group per distinct camera and
index.json (see objcam.transport.storage). Models: ``direct`` (shadow rays, culled; fast), ``path`` (one
path-traced render per texel; the reference), ``auto`` (direct, plus an indirect correction when leaving the
indirect light of sampled columns out would move the fit beyond what the target's noise explains:
objcam.transport.auto).
"""

from __future__ import annotations

import json
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from objcam.errors import StageError
from objcam.pipeline.stage import StageInputs, StageOutputs

NAME = "transport"
DEPS = ("scene",)
VERSION = "2"
# the code whose changes invalidate cached transport artifacts (the solvers too: texel_kernel=auto picks each
# target's A by the default solve's fit, objcam.transport.kernel)
CODE_DEPS = ("objcam.transport", "objcam.render", "objcam.scene", "objcam.envmap", "objcam.camera", "objcam.solvers")


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    model: Literal["auto", "direct", "path"] = "auto"
    env_height: Annotated[int, Field(ge=2)] | Literal["auto"] = Field(
        32, description="envmap rows (width 2x); 'auto': the finest of env_height_candidates the photo supports "
        "(A built at each in turn, a coarse-to-fine test of the quadratic fits: objcam.transport.resolution)")
    env_height_candidates: list[int] = Field([32, 64, 128], min_length=1, description="env_height=auto: the "
                                             "heights tried, coarsest first (each within the machine's memory "
                                             "and env_height_max_seconds, objcam.transport.budget)")
    env_height_max_seconds: float = Field(600.0, gt=0, description="env_height=auto: refuse a height whose "
                                          "planned A, Gram and exact solve take longer (budget's estimate)")
    supersample: int = Field(1, ge=1, le=2, description="build A on a grid this many times finer than env_height; "
                             "the solve resolves sub-texel light where the envmap has contrast and writes the "
                             "envmap area-averaged to env_height (objcam.solvers.refine). 2: the quality setting "
                             "(bench: ~3x the A time, 3-4x the solve time; known albedo only)")
    samples: int = Field(4, ge=1, description="direct: K shadow rays per traced (pixel, texel) pair, from K of "
                                                   "the pixel's sub-pixel samples")
    subpixel_samples: int = Field(32, ge=1, description="direct: S camera rays per pooled pixel (rounded up to a "
                                                         "multiple of K); pairs at shadow boundaries and pixels "
                                                         "mixing surfaces trace one ray per sample. Quality: 64")
    object_samples: int = Field(16, ge=1, description="direct: K for the pixels that see the object")
    object_subpixel_samples: int = Field(256, ge=1, description="direct: S for the pixels that see the object "
                                         "(their faceted normals and silhouette vary inside the pixel)")
    texel_kernel: Annotated[float, Field(gt=0, le=1)] | Literal["auto", "fit"] = Field(
        "auto", description="direct: the shadow rays aim into this central fraction of each texel per side (1: box "
        "texels). 'auto': box texels; each target solved on them, then on A with narrow (0.25) columns at the "
        "solve's compact bright blobs, on A with point sources placed inside their texels by the photo and, where "
        "the solve left black sky, on a whole narrow A, keeping the lowest chi2 (the point sources over the narrow "
        "blob columns where both beat box texels; up to 64 rows, known albedo); 'fit': the whole narrow A for "
        "every target too (objcam.transport.kernel)")
    refine: bool = Field(True, description="direct: pairs at shadow boundaries get one ray per sub-pixel sample")
    downsample: int | Literal["auto"] = Field("auto", description="pool f x f pixel blocks (pool the target with "
                                              "pool_target); 'auto': the smallest f that leaves at most max_pixels "
                                              "pooled pixels (a 128 x 128 target: 1; 640 x 480: 4)")
    max_pixels: int = Field(32768, ge=64, description="downsample=auto: most pooled pixels per camera (a 32 x 64 "
                            "envmap has ~1,100 unknowns; beyond ~16-32k pixels the solve gains little and costs M)")
    seed: int = 0
    variant: Literal["auto", "llvm", "cuda", "scalar"] = Field("auto", description="Mitsuba variant: auto takes "
                                                                "cuda_ad_rgb when a CUDA device is present, else "
                                                                "llvm_ad_rgb (objcam.transport.variant)")
    use_valid: bool = Field(True, description="skip pixels invalid in every target sharing the camera")
    batch_rays: int = Field(1 << 24, ge=1024, description="shadow rays per Mitsuba launch (memory bound)")
    chunk_columns: int = Field(128, ge=1)
    path_spp: int = Field(64, ge=1)
    path_max_depth: int = Field(8, description="Mitsuba path depth (2 = direct light only, -1 = unbounded)")
    path_upsample: int = Field(8, ge=1, description="path renders: box-texel bitmap upsampling (ramps at texel "
                                                    "boundaries 1/upsample texel wide)")
    auto_columns: int = Field(16, ge=1, description="auto: columns sampled to measure indirect light")
    auto_spp: int = Field(32, ge=2)
    auto_max_depth: int = Field(6)
    auto_noise: float | None = Field(None, gt=0, description="auto: relative target noise per photo pixel "
                                                             "(else targets' noise_sigma, else estimated from the "
                                                             "image)")
    correction_scale: int = Field(4, ge=1, description="auto: indirect rendered at 1/scale pooled resolution")
    correction_spp: int = Field(32, ge=1)
    correction_texel_block: int = Field(4, ge=1, description="auto: indirect rendered per g x g texel block "
                                                             "(bilinearly interpolated between blocks)")
    correction_detail_px: int = Field(3, ge=-1, description="auto: pixels within this many (pooled) pixels of the "
                                      "object get their own indirect render, not the coarse image's (-1: none)")
    correction_detail_spp: int = Field(128, ge=1, description="auto: spp of those per-pixel indirect renders")
    indirect: Literal["gather", "path"] = Field("gather", description="auto: how the indirect light is added: "
                                                "'gather' (deterministic: direct light on surface nodes gathered "
                                                "by rays traced once for every column, objcam.transport.gather) or "
                                                "'path' (path-traced correction per texel block, correction_*)")
    gather_rays: int = Field(256, ge=1, description="auto, gather: rays per pixel over its hemisphere")
    gather_node_rays: int = Field(64, ge=1, description="auto, gather: rays per surface node (further bounces)")


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    import time

    from objcam.schemas.artifacts import SceneArtifact
    from objcam.transport.storage import write_index
    from objcam.transport.variant import activate

    t0 = time.perf_counter()
    variant = activate(params.variant, inputs.capture / "capture.toml")  # before the scene is loaded into Mitsuba
    art = SceneArtifact.load(inputs.upstream["scene"])
    groups: dict[str, list] = {}
    for t in art.targets:
        groups.setdefault(json.dumps(t.camera.model_dump(), sort_keys=True), []).append(t)
    by_camera = list(groups.values())  # each camera's targets
    desc = art.description
    if params.supersample > 1 and not (desc.albedo_object.known and desc.albedo_support.known):
        # refused here, before the build, rather than by the solve after it
        raise StageError("transport.supersample > 1 is solved only with a known albedo, and this capture leaves "
                         "the " + ("object's" if not desc.albedo_object.known else "support's") + " albedo unknown",
                         inputs.capture / "capture.toml", "set transport.supersample=1")
    if params.texel_kernel == "fit" and (params.supersample > 1 or params.env_height == "auto"
                                         or params.model == "path"):
        raise StageError("transport.texel_kernel=fit is built for a fixed env_height, supersample 1 and the direct "
                         "or auto model", inputs.capture / "capture.toml", "set transport.texel_kernel=auto")
    choice = None
    if params.env_height == "auto":
        from objcam.transport.resolution import choose_height

        if params.supersample > 1:
            raise StageError("transport.env_height=auto chooses the envmap's own grid and is not combined with "
                             "transport.supersample > 1", inputs.capture / "capture.toml",
                             "set transport.supersample=1, or a fixed transport.env_height")
        height, choice = choose_height(inputs.out, params, art, by_camera,
                                       lambda h: _estimates(params, art, by_camera, h),
                                       lambda h, out: _build_height(inputs, params, art, by_camera, h, out)[:2],
                                       toml=inputs.capture / "capture.toml")
    else:
        height = params.env_height
        _check_budget(inputs, params, art, by_camera, height)
    if choice is None:
        per_cam, mapping, planned = _build_height(inputs, params, art, by_camera, height, inputs.out)
    else:  # built already, moved into place by choose_height
        per_cam, mapping = choice.pop("_built")
        planned = _planned(params, art, by_camera, height)
    write_index(inputs.out, mapping)
    metrics: dict = {}
    first = per_cam[0] if per_cam else {}
    if len(groups) == 1:
        metrics.update(first)
    else:
        for i, m in enumerate(per_cam):
            metrics.update({f"cam{i}.{k}": v for k, v in m.items()})
    totals = {k: sum(int(m.get(k, 0)) for m in per_cam)
              for k in ("pixels_kept", "pixels_total", "rays_traced", "rays_culled")}
    metrics.update(totals)
    metrics["cameras"] = len(groups)
    metrics["variant"] = variant
    metrics["env_height"] = height
    metrics["planned_peak_gib"] = round(planned["bytes"] / 2**30, 6)  # objcam.transport.budget's estimate
    metrics["planned_seconds"] = round(planned["seconds"], 1)
    if choice is not None:
        metrics["env_height_auto"] = choice  # the choice, its measure and its reason (objcam.transport.resolution)
    metrics["seconds_total"] = round(time.perf_counter() - t0, 3)
    chosen = ",".join(sorted({str(m.get("model")) for m in per_cam}))
    k_or_spp = f"K={params.samples}" if params.model != "path" else f"spp={params.path_spp}"
    cams = f", {len(groups)} cameras" if len(groups) > 1 else ""
    summary = (f"A: {totals['pixels_kept']:,} px x {first.get('texels_kept', 0):,} texels ({chosen} {k_or_spp}{cams}) "
               f"in {metrics['seconds_total']:.1f} s")
    if choice is not None:
        summary += f"; env_height auto -> {height}: {choice['reason']}"
    for kind, what in (("narrow", "narrow texel kernel (black sky on box texels)"),
                       ("compact", "compact texel kernel (at compact sources)"),
                       ("point", "point sources placed inside their texels by the photo")):
        names = [n for m in per_cam for n, r in m.get("texel_kernel_auto", {}).get("targets", {}).items()
                 if r["kernel"] == kind]
        if names:
            summary += f"; {what} for {', '.join(names)}"
    return StageOutputs(metrics=metrics, summary=summary)


#: texel_kernel=auto asks the fit up to this envmap height: at 128 rows a box texel (1.4 deg) is already smaller
#: than a lamp of 2 deg, and a pilot solve there takes minutes
AUTO_MAX_HEIGHT = 64


def _estimates(params: Params, art, groups: list[list], height: int) -> list[dict]:
    """objcam.transport.budget's estimate per camera for envmap ``height`` (A on height x supersample rows)."""
    from objcam.transport import budget

    desc = art.description
    out = []
    for cam_targets in groups:
        cam, f = cam_targets[0].camera, downsample_for(cam_targets[0].camera, params)
        out.append(budget.estimate((cam.height // f) * (cam.width // f),
                                   budget.kept_texels(height * params.supersample, desc.support_is_plane),
                                   1 if desc.albedo_is_grey() else 3, targets=len(cam_targets)))
    return out


def _planned(params: Params, art, groups: list[list], height: int) -> dict:
    """The build's plan (objcam.transport.budget.plan: the largest peak, the summed seconds) from its cameras'
    :func:`_estimates`."""
    from objcam.transport import budget

    return budget.plan(_estimates(params, art, groups, height))


def _check_budget(inputs: StageInputs, params: Params, art, groups: list[list], height: int) -> None:
    """Refuse what the machine cannot hold before building (objcam.transport.budget)."""
    from objcam.transport import budget

    for est in _estimates(params, art, groups, height):
        budget.check(est, inputs.capture / "capture.toml")


def _build_height(inputs: StageInputs, params: Params, art, groups: list[list], height: int, out):
    """Build every camera's A for an envmap of ``height`` rows into ``out``/cam<i> (A's grid height x
    supersample, objcam.solvers.refine) with its Gram matrix. Returns (per-camera metrics, {target: "cam<i>"},
    the planned {"bytes", "seconds"})."""
    from objcam.transport.auto import estimate_relative_noise
    from objcam.transport.build import BuildSettings, build_camera
    from objcam.transport.engine import current
    from objcam.transport.geometry import SceneGeometry

    fine_height = height * params.supersample  # A's grid (objcam.solvers.refine)
    planned = _planned(params, art, groups, height)
    geo = SceneGeometry.load(art.description, art.folder, env_height=fine_height, upsample=params.path_upsample)
    per_cam, mapping = [], {}
    for i, targets in enumerate(groups):
        sub = f"cam{i}"
        valids = [t.load_valid(art.folder) for t in targets]
        f = downsample_for(targets[0].camera, params)
        # texel_kernel auto / fit (objcam.transport.kernel); auto is box texels where it does not apply
        by_fit = params.texel_kernel == "fit" or (params.texel_kernel == "auto" and params.supersample == 1
                                                   and params.model != "path" and params.env_height != "auto"
                                                   and height <= AUTO_MAX_HEIGHT)
        settings = BuildSettings(**(params.model_dump(exclude={"max_pixels", "supersample", "variant",
                                                               "env_height_candidates", "env_height_max_seconds"})
                                    | {"downsample": f, "env_height": fine_height, "output_height": height,
                                       "texel_kernel": 1.0 if isinstance(params.texel_kernel, str)
                                       else params.texel_kernel}))
        noise = (_target_noise(art.folder, targets, f, estimate_relative_noise)
                 if params.model == "auto" else None)
        kept: dict = {}
        m = build_camera(geo, targets[0].camera, out / sub, settings, valids=valids,
                         targets=[t.name for t in targets], target_noise=noise, hold=kept)
        m["gram_seconds"] = round(current().write_gram(out / sub), 3)  # objcam.transport.engine
        m.update(current().metrics())
        per_cam.append(m)
        mapping.update({t.name: sub for t in targets})
        if by_fit:
            from objcam.transport.kernel import for_camera

            m.update(for_camera(art, geo, targets, out, sub, settings, valids, noise, m.get("model"),
                                kept.get("direct"), mapping, params.texel_kernel, inputs.capture))
    return per_cam, mapping, planned


def downsample_for(camera, params: Params) -> int:
    """The pooling factor of a camera: ``params.downsample``, or for 'auto' the smallest f with
    (H // f) * (W // f) <= params.max_pixels."""
    if params.downsample != "auto":
        return int(params.downsample)
    f = 1
    while (camera.height // f) * (camera.width // f) > params.max_pixels:
        f += 1
    return f


def _target_noise(folder, targets, f: int, estimator) -> tuple[float, str]:
    """The smallest relative noise per fitted (pooled) pixel among targets sharing a camera: their noise_sigma
    over the pooling factor f, else estimated from the pooled image; 1% when neither is available."""
    from objcam.transport.pixels import pool_target

    given = [t.noise_sigma for t in targets if t.noise_sigma is not None]
    if given:  # noise_sigma is per photo pixel: the mean of f x f of them
        return float(min(given)) / max(int(f), 1), "noise_sigma"
    est = []
    for t in targets:
        try:
            img, ok = pool_target(t.load_image(folder), t.load_valid(folder), f)
        except Exception:
            continue
        e = estimator(img, ok)
        if e is not None:
            est.append(e)
    if est:
        return float(min(est)), "estimated"
    return 0.01, "assumed"
