"""Object and support meshes as PLY, OBJ + MTL (UVs and the albedo texture) and binary glTF, through trimesh.

UVs: objcam's meshes put texel row 0 at v = 0 (image convention, as Mitsuba's bitmap lookup); PLY, OBJ and glTF
readers expect v = 0 at the bottom of the image (OpenGL), so the files hold (u, 1 - v) (trimesh writes glTF's
own top-left origin from that). Vertex order and count are kept exactly (no merging), so the files index the
same vertices as objcam's ``object.npz`` / ``support.npz``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from objcam.image_io import atomic_write_bytes, atomic_write_text


@dataclass
class ExportMesh:
    """One surface to export: mesh (MeshData, world metres), its albedo: a linear RGB constant or a texture
    (Ht, Wt, 3) linear in [0, 1] over the mesh's UVs; ``albedo_source`` says where it came from."""

    name: str
    mesh: object  # objcam.scene.MeshData
    rgb: tuple[float, float, float] | None
    texture: np.ndarray | None
    albedo_source: str


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1), what image viewers and glTF's baseColorTexture expect."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _texture_png(texture: np.ndarray):
    from PIL import Image

    return Image.fromarray((srgb_encode(texture[..., :3]) * 255.0 + 0.5).astype(np.uint8), "RGB")


def trimesh_of(e: ExportMesh):
    """A trimesh.Trimesh of ``e`` (process=False: no vertex merging) with its UVs (OpenGL v) and material."""
    import trimesh
    from trimesh.visual.material import PBRMaterial

    m = e.mesh
    tm = trimesh.Trimesh(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64), process=False)
    if e.texture is not None and m.uv is not None:
        uv = np.column_stack([m.uv[:, 0], 1.0 - m.uv[:, 1]])
        mat = PBRMaterial(name=f"{e.name}_albedo", baseColorTexture=_texture_png(e.texture), metallicFactor=0.0,
                          roughnessFactor=1.0)
        tm.visual = trimesh.visual.TextureVisuals(uv=uv, material=mat)
    else:
        rgb = e.rgb if e.rgb is not None else (0.5, 0.5, 0.5)
        srgb = srgb_encode(np.asarray(rgb, np.float64))
        mat = PBRMaterial(name=f"{e.name}_albedo", baseColorFactor=[*(float(c) for c in srgb), 1.0],
                          metallicFactor=0.0, roughnessFactor=1.0)
        tm.visual = trimesh.visual.TextureVisuals(material=mat)
    return tm


def write_mesh_files(folder: Path, e: ExportMesh) -> list[Path]:
    """``<name>.ply``, ``<name>.obj`` + ``.mtl`` (+ ``<name>_albedo.png``) and ``<name>.glb`` in ``folder``."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    tm = trimesh_of(e)
    out = []
    ply = folder / f"{e.name}.ply"
    atomic_write_bytes(ply, trimesh.exchange.ply.export_ply(tm, encoding="binary", include_attributes=False))
    out.append(ply)
    obj_text, files = trimesh.exchange.obj.export_obj(tm, include_normals=False, include_texture=True,
                                                      return_texture=True, mtl_name=f"{e.name}.mtl",
                                                      header="objcam export (world metres, z up)")
    for fname, data in files.items():
        if fname.endswith(".mtl"):
            continue  # our own below: trimesh's sets Ks 0.4 and Kd 0.4, which darkens the map in most viewers
        atomic_write_bytes(folder / fname, data)
        out.append(folder / fname)
    tex_png = next((p.name for p in out if p.suffix == ".png"), None)
    atomic_write_bytes(folder / f"{e.name}.mtl", _mtl(e, tex_png))
    out.append(folder / f"{e.name}.mtl")
    if "mtllib" not in obj_text:
        obj_text = f"mtllib {e.name}.mtl\nusemtl {e.name}_albedo\n" + obj_text
    obj = folder / f"{e.name}.obj"
    atomic_write_text(obj, obj_text)
    out.append(obj)
    glb = folder / f"{e.name}.glb"
    atomic_write_bytes(glb, trimesh.exchange.gltf.export_glb(trimesh.Scene({e.name: tm})))
    out.append(glb)
    return out


def _mtl(e: ExportMesh, texture_png: str | None) -> bytes:
    """A diffuse material: the albedo texture (sRGB PNG) with Kd 1, or Kd = the linear albedo constant."""
    r, g, b = (1.0, 1.0, 1.0) if texture_png else (e.rgb if e.rgb is not None else (0.5, 0.5, 0.5))
    text = (f"# objcam export: albedo ({e.albedo_source})\nnewmtl {e.name}_albedo\n"
            f"Kd {r:.6f} {g:.6f} {b:.6f}\nKa 0 0 0\nKs 0 0 0\nillum 1\n")
    if texture_png:
        text += f"map_Kd {texture_png}\n"
    return text.encode()
