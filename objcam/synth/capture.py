"""Synthetic known-geometry captures: an object on the plane z = 0 under a bundled (or given) environment map,
path-traced with interreflections and passed through a camera noise model, plus everything the ``evaluate``
stage needs in ``truth/``.

Layout written by :func:`synthesize` (paths relative to the capture folder)::

    capture.toml                  scene, known albedos, targets (the pipeline's only entry point)
    object.ply                    the object, world metres, centred on the origin in x and y, min z exactly 0
    albedo_support.exr            the support's albedo texture (only when patterned and declared known)
    targets/<name>.exr            float32 linear RGB target image (noise model applied)
    targets/<name>.json           its camera (OpenCV convention, objcam.camera.Camera)
    truth/truth.json              what is where (below); never read by the pipeline
    truth/envmap.exr              the rotated full-resolution envmap used, when every target shares one rotation
    truth/<name>/envmap.exr       ... otherwise one per target
    truth/<name>/camera.json      the true camera (identical to targets/<name>.json: no pose noise is simulated)
    truth/<name>/clean.exr        the noise-free render
    truth/<name>/preview.png      tonemapped noisy target, for a look
    truth/albedo_support.exr      the true support texture (also when declared unknown)

``truth/truth.json``: ``envmaps`` {target: path of its envmap} (what ``evaluate`` reads), ``targets`` {target:
rotation, camera, clean image, noise parameters, clipped pixel count}, ``albedo`` {object, support: {"rgb": [..]}
or {"texture": path, "extent": metres, "pattern": name}, plus "known": whether capture.toml declares it},
``object`` (source, height, bounding box), ``envmap`` (source and height), ``render`` (spp, max_depth, seed,
envmap_upsample) and ``noise`` (the model).

Noise model (per pixel and channel, radiance units throughout): electrons ~ Poisson(exposure * radiance), plus
Gaussian read noise of ``read_noise`` electrons, divided by ``exposure``, then clipped at ``white_level``
(pixels at the white level are what capture.toml's ``saturation`` excludes). With ``exposure`` unset it is chosen
so that the median pixel has relative shot noise ``shot_noise`` (1e-3: 10^6 electrons; think of an HDR merge).
Negative values from read noise are kept (unbiased). Each target is rendered as two independent halves of
``spp`` samples; their difference measures the render's own Monte Carlo noise, and capture.toml's ``noise_sigma`` is
hypot(camera noise, render noise), both relative at the median pixel (at the default 512 spp the render noise,
about 2.4% per pixel, dominates the 0.1% camera noise).

The model's functions live in :mod:`objcam.synth.noise`, the envmaps and meshes in :mod:`objcam.synth.assets`.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path
from typing import Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from objcam.camera import Camera, look_at
from objcam.errors import InputError
from objcam.synth.assets import bundled_envmaps, load_envmap, object_mesh, write_ply
from objcam.synth.noise import apply_noise, auto_exposure, mc_noise, relative_noise

RGB = tuple[float, float, float]
Pattern = Literal["checker", "dots"]


# ------------------------------------------------------------------------------------------------- textures


def pattern_texture(pattern: str, size: int, extent: float, seed: int = 0, scale: float = 0.05) -> np.ndarray:
    """A (size, size, 3) float32 albedo texture in [0.05, 0.9] over a square of ``extent`` metres.

    "checker": squares of ``scale`` metres in two colours; "dots": a light ground with dots of 0.3 to 1 times
    ``scale`` in diameter in random colours. 4x4 supersampled (anti-aliased).
    """
    ss = 4
    n = size * ss
    x = (np.arange(n) + 0.5) / n * extent  # metres across the texture
    xx, yy = np.meshgrid(x, x, indexing="xy")
    if pattern == "checker":
        a, b = np.array([0.7, 0.62, 0.5]), np.array([0.25, 0.3, 0.4])
        k = (np.floor(xx / scale) + np.floor(yy / scale)) % 2
        img = np.where(k[..., None] > 0, a, b)
    elif pattern == "dots":
        rng = np.random.default_rng(seed)
        img = np.broadcast_to(np.array([0.6, 0.58, 0.52]), (n, n, 3)).copy()
        n_dots = int(round(1.2 * (extent / scale) ** 2))
        centres = rng.uniform(0, extent, (n_dots, 2))
        radii = rng.uniform(0.15, 0.5, n_dots) * scale
        colours = rng.uniform(0.1, 0.85, (n_dots, 3))
        px = extent / n
        for (cx, cy), r, col in zip(centres, radii, colours):
            i0, i1 = max(0, int((cy - r) / px)), min(n, int((cy + r) / px) + 1)
            j0, j1 = max(0, int((cx - r) / px)), min(n, int((cx + r) / px) + 1)
            inside = (xx[i0:i1, j0:j1] - cx) ** 2 + (yy[i0:i1, j0:j1] - cy) ** 2 <= r * r
            img[i0:i1, j0:j1][inside] = col
    else:
        raise ValueError(f"unknown pattern {pattern!r} (checker, dots)")
    img = img.reshape(size, ss, size, ss, 3).mean(axis=(1, 3))
    return np.clip(img, 0.05, 0.9).astype(np.float32)




# --------------------------------------------------------------------------------------------------- params


class CameraSpec(BaseModel):
    """A target camera: on a sphere around ``target`` (azimuth from +x towards +y, elevation above the ground)
    looking at it, or an explicit ``world_from_camera`` (OpenCV axes)."""

    model_config = ConfigDict(extra="forbid")
    width: int = Field(128, ge=8, le=8192, description="image width, pixels")
    height: int = Field(128, ge=8, le=8192, description="image height, pixels")
    azimuth_deg: float = Field(-90.0, description="camera position azimuth about the target, from +x towards +y")
    elevation_deg: float = Field(40.0, gt=0, lt=90, description="camera elevation above the ground, degrees")
    distance: float = Field(0.4, gt=0, description="camera distance from the target, metres")
    target: tuple[float, float, float] | None = Field(
        None, description="point looked at, metres (default: the object's axis at a quarter of its height)")
    fov_deg: float = Field(45.0, gt=1, lt=170, description="horizontal field of view, degrees (sets fx = fy)")
    fx: float | None = Field(None, gt=0, description="focal length in pixels (overrides fov_deg)")
    fy: float | None = Field(None, gt=0, description="vertical focal length in pixels (default fx)")
    cx: float | None = Field(None, description="principal point column (default (width - 1) / 2)")
    cy: float | None = Field(None, description="principal point row (default (height - 1) / 2)")
    world_from_camera: list[list[float]] | None = Field(None, description="explicit 4x4 pose (OpenCV axes)")

    def camera(self, object_height: float) -> Camera:
        if self.world_from_camera is not None:
            m = np.asarray(self.world_from_camera, dtype=float)
        else:
            tgt = np.array(self.target if self.target is not None else (0.0, 0.0, 0.25 * object_height))
            az, el = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
            eye = tgt + self.distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                  math.sin(el)])
            m = look_at(eye, tgt)
        fx = self.fx if self.fx is not None else (self.width / 2) / math.tan(math.radians(self.fov_deg) / 2)
        fy = self.fy if self.fy is not None else fx
        cx = self.cx if self.cx is not None else (self.width - 1) / 2
        cy = self.cy if self.cy is not None else (self.height - 1) / 2
        return Camera(width=self.width, height=self.height, fx=fx, fy=fy, cx=cx, cy=cy, world_from_camera=m.tolist())


AlbedoParam = Union[float, RGB, Pattern, str]


def _albedo_ok(v, what: str, textures: bool):
    if isinstance(v, str):
        if not textures:
            raise ValueError(f"{what}: textures need mesh UVs, which synth does not make; give a value or [r, g, b]")
        if v in ("checker", "dots"):
            return v
        if not Path(v).is_file():
            raise ValueError(f"{what}: {v!r} is neither 'checker', 'dots' nor an existing EXR texture")
        return v
    vals = [v] if isinstance(v, (int, float)) else list(v)
    if len(vals) not in (1, 3) or any(not (0.0 <= float(x) <= 1.0) for x in vals):
        raise ValueError(f"{what}: albedo values must lie in [0, 1] (a scalar or [r, g, b])")
    return float(vals[0]) if len(vals) == 1 else tuple(float(x) for x in vals)


class SynthParams(BaseModel):
    """Everything that defines a synthetic capture. Defaults: the bunny under ``forest``, one 128 x 128 target."""

    model_config = ConfigDict(extra="forbid")
    object: str = Field("bunny", description="'bunny', 'sphere' or a mesh file (scaled to object_height)")
    object_height: float = Field(0.08, gt=0, le=5, description="object height, metres")
    envmap: str = Field("forest", description="bundled envmap name or an EXR path (standard lat-long file, data_layout.md)")
    envmap_height: int = Field(128, ge=4, le=2048, description="envmap rows used for rendering and as truth")
    rotations_deg: list[float] = Field([0.0], min_length=1,
                                       description="envmap rotations about +z, one set of targets per rotation")
    cameras: list[CameraSpec] = Field([{}], min_length=1, validate_default=True,
                                      description="target cameras: JSON list of objects with keys width, height, "
                                      "azimuth_deg, elevation_deg, distance, target, fov_deg, fx, fy, cx, cy, "
                                      "world_from_camera (objcam.synth.capture.CameraSpec)")
    object_albedo: Union[float, RGB] = Field(0.6, description="scalar or [r, g, b]")
    support_albedo: AlbedoParam = Field(0.5, description="scalar, [r, g, b], 'checker', 'dots' or an EXR path")
    object_albedo_known: bool = Field(True, description="write the object albedo into capture.toml")
    support_albedo_known: bool = Field(True, description="write the support albedo into capture.toml")
    texture_extent: float = Field(1.0, gt=0, description="side of the square the support texture covers, metres")
    texture_size: int = Field(512, ge=8, le=8192, description="support texture resolution, pixels")
    texture_scale: float = Field(0.05, gt=0, description="checker square / dot size of the patterns, metres")
    plane_size: float = Field(20.0, gt=0, description="side of the square support plane, metres")
    spp: int = Field(512, ge=1, description="samples per pixel of the target renders (with estimator 'split': "
                     "of the indirect part)")
    estimator: Literal["path", "split"] = Field(
        "path", description="'path': Mitsuba's path tracer; 'split': direct light by stratified quadrature over "
        "split_strata x 2 split_strata cells per sphere plus path-traced indirect (objcam.synth.split_render; "
        "~10x less noise)")
    split_strata: int = Field(64, ge=8, le=1024, description="theta rows of the direct-light strata ('split')")
    split_budget: float = Field(4.0, gt=0, le=64, description="extra rays for bright strata ('split'; see "
                                "objcam.synth.split_render.direction_strata), shared by the two half renders")
    max_depth: int = Field(6, ge=-1, description="path length (Mitsuba's path integrator; 2 = direct light only)")
    envmap_upsample: int = Field(2, ge=1, le=16, description="objcam.render.mitsuba_box_bitmap factor")
    noise: bool = Field(True, description="apply shot and read noise")
    shot_noise: float = Field(1e-3, gt=0, description="relative shot noise at the median pixel (sets exposure)")
    exposure: float | None = Field(None, gt=0, description="electrons per unit radiance (overrides shot_noise)")
    read_noise: float = Field(100.0, ge=0, description="read noise, electrons")
    white_level: float | None = Field(None, gt=0, description="clip at this radiance (capture saturation)")
    seed: int = Field(0, ge=0, description="seed of the renders, the noise and the dot pattern")

    @field_validator("object")
    @classmethod
    def _object(cls, v: str) -> str:
        if v not in ("bunny", "sphere") and not Path(v).is_file():
            raise ValueError(f"{v!r} is neither 'bunny', 'sphere' nor an existing mesh file")
        return v

    @field_validator("envmap")
    @classmethod
    def _envmap(cls, v: str) -> str:
        if v not in bundled_envmaps() and not Path(v).is_file():
            raise ValueError(f"{v!r} is neither a bundled envmap ({', '.join(bundled_envmaps())}) nor an EXR file")
        return v

    @field_validator("object_albedo", mode="before")
    @classmethod
    def _obj_albedo(cls, v):
        return _albedo_ok(v, "object_albedo", textures=False)

    @field_validator("support_albedo", mode="before")
    @classmethod
    def _sup_albedo(cls, v):
        return _albedo_ok(v, "support_albedo", textures=True)

    @model_validator(mode="after")
    def _names(self):
        if len({_rot_name(r) for r in self.rotations_deg}) != len(self.rotations_deg):
            raise ValueError("rotations_deg has duplicates")
        return self


def _rot_name(deg: float) -> str:
    return f"{deg:g}".replace("+", "")


def target_names(params: SynthParams) -> list[tuple[str, int, float]]:
    """(name, camera index, rotation) of every target: ``t0`` for a single one, else ``cam<j>_rot<deg>``."""
    if len(params.cameras) == 1 and len(params.rotations_deg) == 1:
        return [("t0", 0, params.rotations_deg[0])]
    return [(f"cam{j}_rot{_rot_name(r)}", j, r) for j in range(len(params.cameras)) for r in params.rotations_deg]


# ------------------------------------------------------------------------------------------------- synthesis


def _albedo_value(v, root: Path, name: str, tex: np.ndarray | None):
    """An objcam.scene.AlbedoValue for rendering, writing ``tex`` into ``root`` when the albedo is a texture."""
    from objcam.image_io import write_exr
    from objcam.scene import AlbedoValue

    if tex is not None:
        write_exr(root / f"{name}.exr", tex)
        return AlbedoValue(texture=f"{name}.exr")
    rgb = (v,) * 3 if isinstance(v, float) else tuple(v)
    return AlbedoValue(rgb=rgb)


def _toml_value(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(type(v))


def _seed(seed: int, index: int) -> int:
    return (seed * 1_000_003 + index * 7919 + 17) % (2**31)


def synthesize(out_dir: str | Path, params: SynthParams | None = None) -> dict:
    """Render the synthetic capture ``params`` into ``out_dir`` (created; must be empty if it exists).

    Returns a summary: the targets, image sizes, clipped pixel counts, noise level, and render times.
    """
    from objcam.envmap import rotate_z, write_latlong
    from objcam.image_io import atomic_write_text, read_exr, write_exr, write_tonemapped_png
    from objcam.progress import bar
    from objcam.render import mitsuba_box_bitmap, render_image
    from objcam.synth.split_render import direction_strata, render_split
    from objcam.scene import MeshData, SceneDescription, build_mitsuba_scene, make_plane

    params = params or SynthParams()
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("output folder exists and is not empty", out, "give a new or empty folder")
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    # geometry
    verts, faces = object_mesh(params.object, params.object_height)
    write_ply(out / "object.ply", verts, faces)

    # albedos
    sup_tex = obj_tex = None
    sup = params.support_albedo
    if sup in ("checker", "dots"):
        sup_tex = pattern_texture(sup, params.texture_size, params.texture_extent, params.seed, params.texture_scale)
    elif isinstance(sup, str):
        sup_tex = read_exr(sup)[..., :3]

    truth_albedo: dict = {}
    toml_albedo: dict = {}
    for key, val, tex in (("object", params.object_albedo, obj_tex), ("support", sup, sup_tex)):
        known = params.object_albedo_known if key == "object" else params.support_albedo_known
        if tex is not None:
            write_exr(out / "truth" / f"albedo_{key}.exr", tex)
            entry = {"texture": f"truth/albedo_{key}.exr"}
            if key == "support":
                entry |= {"extent": params.texture_extent, "pattern": val if val in ("checker", "dots") else None}
            if known:
                write_exr(out / f"albedo_{key}.exr", tex)
                toml_albedo[key] = {"texture": f"albedo_{key}.exr"} | (
                    {"extent": params.texture_extent} if key == "support" else {})
        else:
            rgb = [val] * 3 if isinstance(val, float) else list(val)
            entry = {"rgb": rgb}
            if known:
                toml_albedo[key] = val if isinstance(val, float) else list(val)
        truth_albedo[key] = entry | {"known": known}

    # environment
    notes: list[str] = []
    env = load_envmap(params.envmap, params.envmap_height, notes).astype(np.float64)
    targets = target_names(params)
    rotations = sorted({r for _, _, r in targets}, key=params.rotations_deg.index)
    per_target_env = len(rotations) > 1
    cams = [c.camera(params.object_height) for c in params.cameras]

    summary: dict = {"out_dir": str(out), "targets": {}, "render_seconds": 0.0}
    if notes:
        summary["notes"] = notes
    truth_targets: dict = {}
    envmaps_rel: dict = {}
    toml_targets: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="objcam-synth-") as tmp:
        root = Path(tmp)
        MeshData(verts, faces).save(root / "object.npz")
        plane = make_plane(params.plane_size, params.texture_extent if sup_tex is not None else None)
        plane.save(root / "support.npz")
        desc = SceneDescription(object_mesh="object.npz", support_mesh="support.npz", support_is_plane=True,
                                albedo_object=_albedo_value(params.object_albedo, root, "albedo_object", obj_tex),
                                albedo_support=_albedo_value(sup, root, "albedo_support", sup_tex))
        progress = bar(total=len(targets), desc="synth renders", unit="target")

        def render(scene, cam, spp, seed):
            if params.estimator == "split":
                strata = direction_strata(env_rot, params.split_strata, params.split_budget / 2)
                return render_split(scene, cam, spp, params.max_depth, strata, seed=seed)
            return render_image(scene, cam, spp, params.max_depth, seed=seed)

        for rot in rotations:
            env_rot = rotate_z(env, rot).astype(np.float32)
            scene = build_mitsuba_scene(desc, root, envmap=mitsuba_box_bitmap(env_rot, params.envmap_upsample))
            if not per_target_env:
                write_latlong(out / "truth" / "envmap.exr", env_rot)
            for index, (name, j, r) in enumerate(targets):
                if r != rot:
                    continue
                cam = cams[j]
                t0 = time.perf_counter()
                # two independent halves: their mean is the render, their difference measures its Monte Carlo noise
                half = max(1, params.spp // 2)
                a = render(scene, cam, half, _seed(params.seed, 2 * index))
                b = render(scene, cam, params.spp - half if params.spp > 1 else 1, _seed(params.seed, 2 * index + 1))
                w = half / max(params.spp, 2) if params.spp > 1 else 0.5
                clean = (w * a + (1 - w) * b).astype(np.float32)
                dt = time.perf_counter() - t0
                summary["render_seconds"] += dt
                mc = mc_noise(a, b, clean, w)
                exposure = params.exposure or auto_exposure(clean, params.shot_noise)
                rng = np.random.default_rng([params.seed, index])
                img, clipped = apply_noise(clean, exposure, params.read_noise, params.white_level, rng, params.noise)
                pos = clean[clean > 0]
                med = float(np.median(pos)) if pos.size else 0.0
                cam_sigma = relative_noise(med, exposure, params.read_noise) if params.noise and med > 0 else 0.0
                sigma = math.hypot(cam_sigma, mc)

                write_exr(out / "targets" / f"{name}.exr", img)
                cam.save(out / "targets" / f"{name}.json")
                cam.save(out / "truth" / name / "camera.json")
                write_exr(out / "truth" / name / "clean.exr", clean)
                write_tonemapped_png(out / "truth" / name / "preview.png", img)
                if per_target_env:
                    write_latlong(out / "truth" / name / "envmap.exr", env_rot)
                    envmaps_rel[name] = f"truth/{name}/envmap.exr"
                else:
                    envmaps_rel[name] = "truth/envmap.exr"

                entry = {"name": name, "image": f"targets/{name}.exr", "camera": f"targets/{name}.json"}
                if params.white_level is not None:
                    entry["saturation"] = params.white_level
                entry["noise_sigma"] = sigma
                toml_targets.append(entry)
                truth_targets[name] = {
                    "rotation_deg": r, "camera_index": j, "envmap": envmaps_rel[name],
                    "camera": f"truth/{name}/camera.json", "clean_image": f"truth/{name}/clean.exr",
                    "exposure": exposure if params.noise else None, "read_noise": params.read_noise,
                    "white_level": params.white_level, "noise_sigma": sigma, "camera_noise_sigma": cam_sigma,
                    "render_noise_sigma": mc, "median_radiance": med,
                    "n_clipped": int(clipped.sum()), "render_seconds": dt,
                }
                summary["targets"][name] = {"size": [cam.width, cam.height], "rotation_deg": r,
                                            "n_clipped": int(clipped.sum()), "noise_sigma": sigma,
                                            "render_seconds": round(dt, 2)}
                progress.update(1)
        progress.close()

    order = {name: i for i, (name, _, _) in enumerate(targets)}
    toml_targets.sort(key=lambda t: order[t["name"]])
    lines = ["# objcam synthetic capture (objcam.synth); truth/ is for `objcam evaluate` only", "",
             "[scene]", 'object = "object.ply"', 'support = "plane"',
             f"plane_size = {_toml_value(params.plane_size)}"]
    if toml_albedo:
        lines += ["", "[albedo]"] + [f"{k} = {_toml_value(v)}" for k, v in toml_albedo.items()]
    for t in toml_targets:
        lines += ["", "[[targets]]"] + [f"{k} = {_toml_value(v)}" for k, v in t.items()]
    atomic_write_text(out / "capture.toml", "\n".join(lines) + "\n")

    lo, hi = verts.min(axis=0), verts.max(axis=0)
    truth = {
        "format": 1,
        "envmaps": envmaps_rel,
        "targets": truth_targets,
        "albedo": truth_albedo,
        "object": {"source": params.object, "height_m": params.object_height, "mesh": "object.ply",
                   "bbox_min": lo.tolist(), "bbox_max": hi.tolist(), "faces": int(len(faces))},
        "envmap": {"source": params.envmap, "height": int(env.shape[0]), "convention": "standard lat-long (data_layout.md)",
                   "rotation": "objcam.envmap.rotate_z(source, rotation_deg)"},
        "plane_size": params.plane_size,
        "render": {"integrator": "path", "estimator": params.estimator, "spp": params.spp, "max_depth": params.max_depth, "seed": params.seed,
                   "envmap_upsample": params.envmap_upsample, "pixel_filter": "box"},
        "noise": {"enabled": params.noise, "model": "Poisson(exposure * L) + N(0, read_noise^2) electrons, "
                  "/ exposure, min(., white_level)", "shot_noise": params.shot_noise,
                  "read_noise": params.read_noise, "white_level": params.white_level},
        "params": params.model_dump(mode="json"),
    }
    atomic_write_text(out / "truth" / "truth.json", json.dumps(truth, indent=2))
    summary["render_seconds"] = round(summary["render_seconds"], 2)
    summary["total_seconds"] = round(time.perf_counter() - t_start, 2)
    return summary
