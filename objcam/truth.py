"""A synthetic capture's truth (``truth/``, data_layout.md): truth.json, the true envmap of a target, and the true
albedo per pixel rendered the way the transport stage renders a known albedo. Read only by ``evaluate``."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from objcam.errors import InputError
from objcam.image_io import read_exr, write_exr


def truth_meta(capture: Path) -> dict | None:
    """truth/truth.json as a dict (None when absent); an InputError naming it when it is not a JSON object."""
    meta = Path(capture) / "truth" / "truth.json"
    if not meta.is_file():
        return None
    try:
        info = json.loads(meta.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"truth.json is not valid JSON ({str(e)[:80]})", meta,
                         "rewrite it (objcam synth writes it) or remove truth/") from None
    if not isinstance(info, dict) or not isinstance(info.get("envmaps", {}), dict) \
            or not isinstance(info.get("albedo", {}) or {}, dict):
        raise InputError("truth.json is not an object with 'envmaps' and 'albedo' objects", meta,
                         "see truth/ in data_layout.md, or remove truth/")
    return info


def truth_envmap_path(capture: Path, target: str) -> Path | None:
    """Where a synthetic capture keeps the true envmap of ``target`` (see data_layout.md, truth/)."""
    from objcam.pipeline.inputs import check_input

    info = truth_meta(capture)
    if info is not None:
        rel = info.get("envmaps", {}).get(target)
        if rel:
            if not isinstance(rel, str):
                raise InputError(f"truth.json envmaps.{target} is not a path", capture / "truth" / "truth.json")
            if not check_input(capture / rel, capture):
                raise InputError("truth envmap named in truth.json not found", capture / rel)
            return capture / rel
    for cand in (capture / "truth" / target / "envmap.exr", capture / "truth" / "envmap.exr"):
        if cand.is_file():
            return cand
    return None


def truth_albedo_entry(e, key: str, capture: Path) -> dict | None:
    """truth.json ``albedo.<key>`` as ``{"rgb": [r, g, b]}`` or ``{"texture": path, "extent": m}`` (None when
    absent). Accepted forms: a number, an RGB list, ``{"rgb": number or list}``, ``{"texture": ...}``; anything
    else is a one-line InputError naming truth.json."""
    if e is None:
        return None
    meta = Path(capture) / "truth" / "truth.json"
    fix = "write it as [r, g, b], {\"rgb\": [r, g, b]} or {\"texture\": PATH, \"extent\": METRES} (data_layout.md)"
    if isinstance(e, dict) and e.get("texture"):
        return e
    rgb = e.get("rgb") if isinstance(e, dict) else e
    if isinstance(rgb, (int, float)) and not isinstance(rgb, bool):
        rgb = [rgb] * 3
    if not (isinstance(rgb, list) and len(rgb) == 3 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                            and np.isfinite(v) for v in rgb)):
        raise InputError(f"truth.json albedo.{key} is not an albedo", meta, fix)
    return {"rgb": [float(v) for v in rgb]}


def truth_albedo_image(capture: Path, scene_folder: Path, transport) -> np.ndarray | None:
    """(H', W', 3) true albedo at the transport's kept pixels (0 elsewhere), or None without truth albedo.

    Renders the truth's albedo (truth/truth.json ``albedo``: rgb or a texture, with ``extent`` for the plane) with
    the primary samples of the transport stage (objcam.transport.geometry.primary_samples: same camera, pooling,
    sub-pixel sample count and seed), so a pixel's truth is the footprint average the transport's albedo is.
    """
    from objcam.scene import AlbedoValue, MeshData, SceneDescription, make_plane
    from objcam.transport.geometry import SceneGeometry, primary_samples

    info = truth_meta(capture)
    if info is None:
        return None
    meta = info.get("albedo") or {}
    desc = SceneDescription.model_validate_json((scene_folder / "scene.json").read_text())
    with tempfile.TemporaryDirectory(prefix="objcam-truth-albedo-") as tmp:
        root = Path(tmp)
        shutil.copy(scene_folder / desc.object_mesh, root / "object.npz")
        shutil.copy(scene_folder / desc.support_mesh, root / "support.npz")
        values = {}
        for key, have in (("object", desc.albedo_object), ("support", desc.albedo_support)):
            e = truth_albedo_entry(meta.get(key), key, capture)
            if e is None:
                if not have.known:
                    return None  # unknown and no truth for it
                src = scene_folder / have.texture if have.texture else None
                if src is not None:
                    shutil.copy(src, root / f"albedo_{key}.exr")
                values[key] = AlbedoValue(texture=f"albedo_{key}.exr") if src is not None else AlbedoValue(rgb=have.rgb)
                continue
            if e.get("texture"):
                from objcam.pipeline.inputs import check_input

                check_input(capture / str(e["texture"]), capture)  # inside the capture, a regular file
                write_exr(root / f"albedo_{key}.exr", read_exr(capture / e["texture"])[..., :3])
                values[key] = AlbedoValue(texture=f"albedo_{key}.exr")
                if key == "support" and desc.support_is_plane and e.get("extent"):
                    # the scene made the plane without a texture: give it the UVs of the truth's texture extent
                    v = MeshData.load_npz(root / "support.npz").vertices
                    make_plane(float(v[:, 0].max() - v[:, 0].min()), float(e["extent"])).save(root / "support.npz")
            else:
                values[key] = AlbedoValue(rgb=tuple(float(x) for x in e["rgb"]))
        d2 = desc.model_copy(update={"object_mesh": "object.npz", "support_mesh": "support.npz",
                                     "albedo_object": values["object"], "albedo_support": values["support"]})
        geo = SceneGeometry.load(d2, root)
        n = int(transport.attrs.get("subpixel_samples") or 32)
        s = primary_samples(geo, transport.camera, transport.downsample, n, transport.pixel_index,
                            transport.image_shape[1], int(transport.attrs.get("seed") or 0))
        alb = s.albedo()
    img = np.zeros((transport.image_shape[0] * transport.image_shape[1], 3), np.float32)
    img[transport.pixel_index] = alb
    return img.reshape(transport.image_shape[0], transport.image_shape[1], 3)
