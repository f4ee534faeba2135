"""Read a finished work folder and write every export (objcam.export's modules) into OUT:

    OUT/envmaps/<target>.exr, .hdr, _mitsuba.exr   the recovered envmaps (standard lat-long convention)
    OUT/meshes/object.{ply,obj,mtl,glb}, support.*, <name>_albedo.png / .exr   surfaces and albedo
    OUT/images/<target>.exr, .png, views/<stem>.png  the target photos (linear; tonemapped), the SfM views
    OUT/colmap/cameras.txt, images.txt, points3D.txt the cameras as a COLMAP text model
    OUT/transforms.json                              the cameras, nerfstudio style
    OUT/mitsuba/<target>.xml                         a Mitsuba 3 scene per target (renders the solve's prediction)
    OUT/blender_scene.py                             builds the scene in Blender
    OUT/export.json                                  what was written, from what, and the conventions
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from objcam.errors import ObjcamError

MARKER = "export.json"


@dataclass
class ExportOptions:
    upsample: int = 1  # envmap EXR/HDR texels repeated this many times per side (display)
    spp: int = 256  # the Mitsuba scenes' default samples per pixel


def _prepare_out(out: Path) -> None:
    """OUT must be new, empty, or an earlier export (its files are replaced); never anything else."""
    if out.exists() and (not out.is_dir() or out.is_symlink()):
        raise ObjcamError("export folder is not a folder", out, "give a new folder")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise ObjcamError("export folder is not empty and holds no earlier export", out,
                          "give a new or empty folder (objcam replaces what it exports there)")
    out.mkdir(parents=True, exist_ok=True)


def _albedo(value, scene_folder: Path) -> tuple[tuple | None, np.ndarray | None, str]:
    """(rgb, texture, source) of a scene albedo: known constant or texture; unknown: its initial estimate
    (texture stage) when there is one, else grey 0.5 as a placeholder."""
    from objcam.image_io import read_exr

    tex = value.texture or value.initial
    if value.rgb is not None:
        return tuple(float(c) for c in value.rgb), None, "known"
    if tex is not None:
        img = read_exr(scene_folder / tex)[..., :3]
        img = np.repeat(img[..., :1], 3, axis=2) if img.shape[2] == 1 else img
        return None, np.clip(img, 0.0, None), "known texture" if value.texture else "initial estimate (texture stage)"
    return None, None, "unknown: grey 0.5 placeholder (the solve estimated it per pixel, not on the mesh)"


def _json(path: Path) -> dict:
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}


def _fit_scale(xml: Path, prediction: Path, downsample: int, spp: int = 64) -> np.ndarray:
    """(3,) least-squares factors per channel taking the scene ``xml`` rendered by Mitsuba (pooled f x f) to the
    solve's prediction over the pixels it predicts."""
    from objcam.image_io import read_exr
    from objcam.scene import use_mitsuba

    mi = use_mitsuba()
    img = np.asarray(mi.render(mi.load_file(str(xml), spp=spp)), np.float64)[..., :3]
    pred = read_exr(prediction)[..., :3].astype(np.float64)
    h, w, f = pred.shape[0], pred.shape[1], int(downsample)
    pooled = img[: h * f, : w * f].reshape(h, f, w, f, 3).mean(axis=(1, 3))
    used = np.any(pred != 0, axis=2)
    r, p = pooled[used], pred[used]
    den = (r * r).sum(axis=0)
    return np.where(den > 0, (r * p).sum(axis=0) / np.maximum(den, 1e-300), 1.0)


def _view_cameras(work: Path) -> dict:
    """sfm's view cameras when the capture was photographed (name -> Camera)."""
    from objcam.camera import Camera

    folder = work / "sfm" / "cameras" / "views"
    return {f"views/{p.stem}": Camera.model_validate_json(p.read_text()) for p in sorted(folder.glob("*.json"))}


def export_capture(work: Path, out: Path, opts: ExportOptions | None = None) -> dict:
    """Write every export of the work folder ``work`` into ``out``; returns export.json's content."""
    from objcam.export.bake import albedo_views, bake_albedo
    from objcam.export.blender import write_blender_script
    from objcam.export.cameras import write_colmap_text, write_transforms_json
    from objcam.export.envmaps import write_envmap
    from objcam.export.meshes import ExportMesh, write_mesh_files
    from objcam.export.mitsuba_xml import write_scene_xml
    from objcam.export.scale import bounce_scale
    from objcam.image_io import atomic_write_bytes, atomic_write_text, read_exr, write_exr, write_tonemapped_png
    from objcam.schemas.artifacts import SceneArtifact
    from objcam.scene import MeshData
    from objcam.transport import load_transport

    opts = opts or ExportOptions()
    work, out = Path(work), Path(out)
    for stage in ("scene", "transport", "solve"):
        if not (work / stage / "stage.json").is_file():
            raise ObjcamError(f"no finished {stage} stage in the work folder", work / stage,
                              "run `objcam run CAPTURE` (or give its --work DIR) before exporting")
    scene = SceneArtifact.load(work / "scene")
    _prepare_out(out)
    files: list[Path] = []
    record: dict = {"format": 1, "work": str(work), "envmap_convention": "standard lat-long (data_layout.md): "
                    "u = 0.5 - atan2(y, x) / (2 pi), row 0 the zenith", "world": "metres, z up", "targets": {},
                    "meshes": {}, "warnings": []}
    # surfaces: an unknown albedo is baked from the solve's per-pixel estimate (objcam.export.bake)
    transports = {t.name: load_transport(work / "transport", t.name, load_A=False) for t in scene.targets}
    downsample = {name: int(tr.downsample) for name, tr in transports.items()}
    # a scale-ambiguous solve's albedo at the scale its A's interreflections assumed (objcam.export.scale)
    scales = {t.name: bounce_scale(transports[t.name], work / "solve" / t.name) for t in scene.targets}
    meshes = {"object": MeshData.load_npz(scene.folder / scene.description.object_mesh),
              "support": MeshData.load_npz(scene.folder / scene.description.support_mesh)}
    views, unbaked, baked_any, shapes = None, False, False, []
    for name, value in (("object", scene.description.albedo_object), ("support", scene.description.albedo_support)):
        mesh, baked = meshes[name], None
        if not value.known:
            views = (albedo_views(work / "solve", scene.targets, downsample, {n: b.k for n, b in scales.items()})
                     if views is None else views)
            baked = bake_albedo(mesh, [m for k, m in meshes.items() if k != name], views) if views else None
        if baked is not None:
            mesh, rgb, tex, source = baked.mesh, None, baked.texture, "baked from the solve's per-pixel albedo"
            baked_any = True
        else:
            rgb, tex, source = _albedo(value, scene.folder)
            unbaked = unbaked or not value.known
        if tex is not None and mesh.uv is None:
            record["warnings"].append(f"{name}: albedo texture without UVs on the mesh: exported as its mean")
            rgb, tex = tuple(float(c) for c in tex.reshape(-1, 3).mean(axis=0)), None
        files += write_mesh_files(out / "meshes", ExportMesh(name, mesh, rgb, tex, source))
        tex_rel = None
        if tex is not None:
            write_exr(out / "meshes" / f"{name}_albedo.exr", tex.astype(np.float32))
            files.append(out / "meshes" / f"{name}_albedo.exr")
            tex_rel = f"../meshes/{name}_albedo.exr"
        # a baked texture is looked up without interpolation: a bilinear lookup would mix neighbouring pixels' albedo
        shapes.append((name, f"../meshes/{name}.obj", rgb, tex_rel, baked is not None))
        record["meshes"][name] = {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
                                  "albedo": list(rgb) if rgb is not None else "texture", "albedo_source": source}
        if baked is not None:
            record["meshes"][name]["bake"] = baked.record
        elif not value.known:
            record["warnings"].append(f"{name} albedo unknown: exported as its {source.split(':')[0]}; no camera's "
                                      "estimated albedo sees it, so the Mitsuba scenes only approximate the solve's "
                                      "prediction")
    # envmaps, images, Mitsuba scenes
    cameras, image_names = {}, {}
    for t in scene.targets:
        sdir = work / "solve" / t.name
        if not (sdir / "envmap.exr").is_file():
            raise ObjcamError(f"no envmap for target {t.name}", sdir / "envmap.exr", "rerun `objcam run CAPTURE`")
        # already the standard file convention; divided by the factor the baked albedo was multiplied by
        env = read_exr(sdir / "envmap.exr")[..., :3]
        if baked_any and scales[t.name].k != 1.0:
            env = (env / np.float32(scales[t.name].k)).astype(np.float32)
        files += write_envmap(out / "envmaps", t.name, env, opts.upsample)
        img = t.load_image(scene.folder)
        write_exr(out / "images" / f"{t.name}.exr", img)
        write_tonemapped_png(out / "images" / f"{t.name}.png", img)
        files += [out / "images" / f"{t.name}.exr", out / "images" / f"{t.name}.png"]
        cameras[t.name], image_names[t.name] = t.camera, f"images/{t.name}.png"
        tr = transports[t.name]
        depth = 2 if tr.model == "direct" else int(tr.max_depth or 6)
        xml = write_scene_xml(out / "mitsuba" / f"{t.name}.xml", t.camera, t.name,
                              f"../envmaps/{t.name}_mitsuba.exr", shapes, depth, opts.spp)
        files.append(xml)
        record["targets"][t.name] = {"envmap": f"envmaps/{t.name}.exr", "envmap_hdr": f"envmaps/{t.name}.hdr",
                                     "envmap_height": int(env.shape[0]), "upsample": opts.upsample,
                                     "mitsuba": f"mitsuba/{t.name}.xml", "max_depth": depth,
                                     "transport_model": tr.model, "downsample": int(tr.downsample),
                                     "prediction": str(sdir / "prediction.exr")}
        if baked_any:
            record["targets"][t.name].update(scales[t.name].record)
        sinfo = _json(sdir / "solve.json")
        if unbaked and sinfo.get("albedo") == "unknown" and sinfo.get("scale_ambiguous"):
            # envmap and albedo are known only up to one scale per channel, and the exported albedo (the texture
            # stage's estimate) is not the solve's: choose that scale so the exported scene renders the prediction
            s = _fit_scale(xml, sdir / "prediction.exr", int(tr.downsample))
            files += write_envmap(out / "envmaps", t.name, env * s, opts.upsample)
            s = s / scales[t.name].k if baked_any else s  # relative to the solve's envmap
            record["targets"][t.name]["envmap_scale"] = s.tolist()
            record["warnings"].append(f"{t.name}: envmap and albedo known only up to scale (no pixel of known "
                                      f"albedo): the exported envmap is the solve's x {np.round(s, 4).tolist()}, "
                                      "fitted so the Mitsuba scene with the exported albedo renders the prediction")
        if abs(t.camera.fx - t.camera.fy) > 1e-6 * t.camera.fx:
            record["warnings"].append(f"{t.name}: fx != fy; Mitsuba's and Blender's cameras take fx (square pixels)")
    # cameras (targets, and the photogrammetry views when there are any)
    views = _view_cameras(work)
    src_views = work / "ingest" / "views"
    for name, cam in views.items():
        png = src_views / f"{name.split('/', 1)[1]}.png"  # ingest's sRGB copy, the size sfm's camera has
        if png.is_file():
            atomic_write_bytes(out / "images" / f"{name}.png", png.read_bytes())
            files.append(out / "images" / f"{name}.png")
        cameras[name], image_names[name] = cam, f"images/{name}.png"
    files += write_colmap_text(out / "colmap", cameras, image_names)
    files.append(write_transforms_json(out / "transforms.json", cameras, image_names))
    first = scene.targets[0].name
    blender_meshes = [{"obj": obj[3:], "texture": tex[3:] if tex else None, "rgb": list(rgb) if rgb else None,
                       "nearest": nearest} for _, obj, rgb, tex, nearest in shapes]  # paths from OUT: drop "../"
    files.append(write_blender_script(out / "blender_scene.py", f"envmaps/{first}.exr", blender_meshes, cameras,
                                      record["targets"][first]["max_depth"], opts.spp))
    record["cameras"] = sorted(cameras)
    record["files"] = sorted(str(p.relative_to(out)) for p in set(files))
    atomic_write_text(out / MARKER, json.dumps(record, indent=2))
    return record
