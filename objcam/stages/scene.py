"""Stage ``scene``: validate a capture and normalise it into the scene artifact every later stage reads.

Known-geometry capture: reads capture.toml, the meshes, albedo textures, target images and cameras. Photographed
capture: the same, with what the photo stages made in place of what the manifest does not state: target images
from ``ingest``, cameras from ``sfm``, meshes from ``geometry`` (with ``texture``'s UVs), and texture's albedo
estimate as the starting albedo of surfaces whose albedo is unknown. Checks each input and fails with one line
naming the file and the fix; writes world-metre meshes, the scene description and every target's linear image
and valid-pixel mask (see objcam/schemas/artifacts.py). Nothing in the capture folder is written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from objcam.camera import Camera
from objcam.errors import InputError
from objcam.image_io import atomic_write_text, read_exr, write_exr, write_png
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.scene import AlbedoValue, MeshData, SceneDescription, load_mesh, make_plane
from objcam.schemas.artifacts import TargetRecord
from objcam.schemas.capture import CaptureManifest, TextureAlbedo, UniformAlbedo
from objcam.target_checks import check_in_view, check_negatives, hot_pixels, read_target

NAME = "scene"
DEPS: tuple[str, ...] = ()
OPTIONAL_DEPS: tuple[str, ...] = ("ingest", "sfm", "geometry", "texture")
VERSION = "3"

# An object taller than this is almost surely in millimetres or centimetres, not metres.
MAX_PLAUSIBLE_OBJECT_SIZE_M = 5.0


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ground_tolerance: float = 0.005  # metres: how far the object's lowest point may sit from z = 0


def input_files(capture: Path) -> list[Path]:
    """Every capture file this stage reads (their contents key the cache)."""
    capture = Path(capture)
    files = [capture / "capture.toml"]
    try:
        m = CaptureManifest.load(capture)
    except InputError:
        return files  # run() reports the error
    if m.scene.object is not None:
        files.append(capture / m.scene.object)
    if m.scene.support != "plane":
        files.append(capture / m.scene.support)
    for a in (m.albedo.object, m.albedo.support):
        if isinstance(a, TextureAlbedo):
            files.append(capture / a.texture)
    for t in m.targets:
        files += [capture / f for f in (t.image, t.camera, t.mask) if f]
    return files


def _check_object(mesh: MeshData, path: Path, tol: float) -> None:
    lo, hi = mesh.bbox
    size = float(np.max(hi - lo))
    if size > MAX_PLAUSIBLE_OBJECT_SIZE_M:
        unit = "millimetres" if size > 50 else "centimetres"
        raise InputError(f"object is {size:.4g} units across: looks like {unit}, objcam expects metres", path,
                         "rescale the mesh to metres")
    if size <= 0:
        raise InputError("object mesh is degenerate (zero size)", path)
    if abs(float(lo[2])) > max(tol, 0.02 * size):
        raise InputError(f"object's lowest point is at z = {lo[2]:.4g} m, not on the support plane z = 0", path,
                         "translate the mesh so it rests on z = 0 (world frame: metres, z up)")


def _check_plane(size: float, obj: MeshData, toml: Path) -> None:
    """The plane must reach past the object's footprint (its shadows fall around it)."""
    lo, hi = obj.bbox
    reach = 2.0 * float(np.max(np.abs(np.concatenate([lo[:2], hi[:2]]))))
    if size < reach:
        raise InputError(f"plane_size {size:.4g} m does not cover the object's footprint ({reach:.4g} m across)",
                         toml, "give the support plane's real side in metres (default 20)")


def _albedo(spec, capture: Path, out: Path, name: str) -> AlbedoValue:
    if spec is None:
        return AlbedoValue()
    if isinstance(spec, float):
        return AlbedoValue(rgb=(spec, spec, spec))
    if isinstance(spec, tuple):
        return AlbedoValue(rgb=spec)
    if isinstance(spec, UniformAlbedo):
        return AlbedoValue(uniform=True)
    tex = read_exr(capture / spec.texture)
    if not np.all(np.isfinite(tex)) or tex.min() < 0:
        raise InputError("albedo texture has negative, NaN or infinite values", capture / spec.texture,
                         "albedo must lie in [0, 1]")
    if tex.max() > 1.0 + 1e-3:
        raise InputError(f"albedo texture exceeds 1 (max {tex.max():.3g})", capture / spec.texture,
                         "store linear albedo in [0, 1]")
    tex = tex[..., :3] if tex.shape[2] >= 3 else np.repeat(tex[..., :1], 3, axis=2)
    fname = f"albedo_{name}.exr"
    write_exr(out / fname, tex)
    return AlbedoValue(texture=fname)


def _target_sources(spec, capture: Path, upstream: dict[str, Path]) -> tuple[Path, Path, Path | None]:
    """Camera file, image file and an upstream valid mask (or None) of one target."""
    if spec.camera is not None:
        cam_path = capture / spec.camera
    elif "sfm" in upstream:
        cam_path = upstream["sfm"] / "cameras" / "targets" / f"{spec.name}.json"
        if not cam_path.is_file():
            raise InputError(f"structure from motion could not pose target {spec.name!r}", capture / spec.folder,
                             "see objcam/sfm/report.json; take the target photo with more of the board in view")
    else:
        raise InputError(f"target {spec.name!r} has no camera", capture / "capture.toml",
                         "give its camera file, or [views] for structure from motion")
    if spec.image is not None:
        return cam_path, capture / spec.image, None
    folder = upstream["ingest"] / "targets" / spec.name
    return cam_path, folder / "image.exr", folder / "valid.png"


def _target(spec, capture: Path, out: Path, upstream: dict[str, Path], obj: MeshData) -> tuple[TargetRecord, dict]:
    import cv2

    cam_path, img_path, upstream_valid = _target_sources(spec, capture, upstream)
    cam = Camera.load(cam_path)
    check_in_view(cam, obj.vertices, cam_path)
    img = read_target(img_path, spec.encoding) if spec.image is not None else read_exr(img_path)
    h, w = img.shape[:2]
    if (w, h) != (cam.width, cam.height):
        raise InputError(f"image is {w}x{h} but its camera says {cam.width}x{cam.height}", img_path,
                         f"use the camera file that took this image, or fix width/height in {cam_path.name}")
    if img.shape[2] not in (1, 3, 4):
        raise InputError(f"image has {img.shape[2]} channels", img_path, "give an RGB or grey linear image")
    rgb = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
    finite = np.isfinite(rgb).all(axis=2)
    if not finite.all():
        n = int((~finite).sum())
        raise InputError(f"image has {n} NaN or infinite pixels", img_path,
                         "re-export it, or mark those pixels invalid in a mask and set them to 0")
    valid = np.ones((h, w), bool)
    if upstream_valid is not None:  # ingest flagged pixels saturated in every frame of the bracket
        valid &= cv2.imread(str(upstream_valid), cv2.IMREAD_UNCHANGED) > 127
    if spec.saturation is not None:
        valid &= ~(rgb >= spec.saturation).any(axis=2)
    if spec.mask:
        mpath = capture / spec.mask
        mask = cv2.imread(str(mpath), cv2.IMREAD_UNCHANGED)
        if mask is None:
            raise InputError("mask cannot be read", mpath, "give a PNG, nonzero = usable pixel")
        if mask.shape[:2] != (h, w):
            raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, image is {w}x{h}", mpath)
        valid &= (mask.reshape(h, w, -1) > 0).any(axis=2)
    if not valid.any():
        raise InputError("no usable pixel (all saturated or masked)", img_path,
                         "use a shorter exposure or check the mask")
    found = check_negatives(rgb, valid, spec.noise_sigma, img_path)  # zero-mean noise is kept: it is data
    hot = hot_pixels(rgb, valid, img_path)
    valid &= ~hot
    found["hot_pixels_excluded"] = int(hot.sum())
    rel = Path("targets") / spec.name
    write_exr(out / rel / "image.exr", rgb)
    write_png(out / rel / "valid.png", valid.astype(np.float64))
    return TargetRecord(name=spec.name, camera=cam, image=str(rel / "image.exr"), valid=str(rel / "valid.png"),
                        illumination=spec.illumination_name, saturation=spec.saturation,
                        noise_sigma=spec.noise_sigma, n_valid=int(valid.sum()), n_pixels=h * w,
                        radiometry=spec.radiometry or ("absolute" if spec.image is not None else "relative")), found


def _is_plane(mesh: MeshData, tol: float = 1e-6) -> bool:
    """True when every vertex lies on z = 0 (the geometry stage's planar support)."""
    return bool(np.abs(mesh.vertices[:, 2]).max() <= tol)


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    capture, out, up = inputs.capture, inputs.out, inputs.upstream
    manifest = CaptureManifest.load(capture)
    # meshes: from the photos (texture's copies carry UVs) when the capture has views, else from the manifest
    mesh_dir = up.get("texture") or up.get("geometry")
    if mesh_dir is not None:
        obj_path = mesh_dir / "object.npz"
        obj = MeshData.load_npz(obj_path)
    else:
        obj_path = capture / manifest.scene.object
        obj = load_mesh(obj_path)
    _check_object(obj, obj_path, params.ground_tolerance)
    obj.save(out / "object.npz")

    tex_extent = None
    if isinstance(manifest.albedo.support, TextureAlbedo):
        tex_extent = manifest.albedo.support.extent
    if mesh_dir is not None:
        support = MeshData.load_npz(mesh_dir / "support.npz")
    elif manifest.scene.support == "plane":
        _check_plane(manifest.scene.plane_size, obj, capture / "capture.toml")
        support = make_plane(manifest.scene.plane_size, tex_extent)
    else:
        support = load_mesh(capture / manifest.scene.support)
    support.save(out / "support.npz")

    desc = SceneDescription(
        object_mesh="object.npz", support_mesh="support.npz",
        support_is_plane=manifest.scene.support == "plane" if mesh_dir is None else _is_plane(support),
        albedo_object=_albedo(manifest.albedo.object, capture, out, "object"),
        albedo_support=_albedo(manifest.albedo.support, capture, out, "support"),
    )
    if "texture" in up:  # photogrammetry's albedo: the starting point of surfaces whose albedo is unknown
        for which in ("object", "support"):
            a = getattr(desc, f"albedo_{which}")
            src = up["texture"] / f"albedo_{which}.exr"
            if not a.known and src.is_file():
                write_exr(out / f"initial_albedo_{which}.exr", read_exr(src)[..., :3])
                a.initial = f"initial_albedo_{which}.exr"
    for which, a in (("object", desc.albedo_object), ("support", desc.albedo_support)):
        if a.texture and which == "object" and obj.uv is None:
            raise InputError("object albedo is a texture but the mesh has no UVs", obj_path,
                             "export the mesh with texture coordinates, or give a constant albedo")
    atomic_write_text(out / "scene.json", desc.model_dump_json(indent=2))

    checked = [_target(t, capture, out, up, obj) for t in manifest.targets]
    targets = [t for t, _ in checked]
    atomic_write_text(out / "targets.json", json.dumps([t.model_dump() for t in targets], indent=2))

    lo, hi = obj.bbox
    unknown = [w for w, a in (("object", desc.albedo_object), ("support", desc.albedo_support)) if not a.known]
    metrics = {
        "object_faces": int(len(obj.faces)),
        "object_height_m": float(hi[2] - lo[2]),
        "targets": len(targets),
        "valid_pixel_fraction": float(sum(t.n_valid for t in targets) / sum(t.n_pixels for t in targets)),
        "unknown_albedo": unknown,
        "target_checks": {t.name: found for t, found in checked},
    }
    notes = [f"{t.name}: {f['hot_pixels_excluded']} hot pixel(s) excluded" for t, f in checked
             if f["hot_pixels_excluded"]]
    notes += [f"{t.name}: {f['negative_pixels']:,} negative pixel(s) kept (within the noise)" for t, f in checked
              if f["negative_pixels"]]
    uniform = [w for w, a in (("object", desc.albedo_object), ("support", desc.albedo_support)) if a.uniform]
    if uniform:
        metrics["uniform_albedo"] = uniform
    said = [f"{w} (one colour)" if w in uniform else w for w in unknown]
    summary = (f"{len(obj.faces):,} faces, {metrics['object_height_m'] * 100:.1f} cm tall; {len(targets)} target(s)"
               + (f"; unknown albedo: {', '.join(said)}" if unknown else "") + "".join(f"; {n}" for n in notes))
    return StageOutputs(metrics=metrics, summary=summary)
