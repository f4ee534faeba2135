"""Scene geometry and materials: meshes as numpy arrays, a JSON scene description, and its Mitsuba 3 scene.

The scene description is what the transport stage consumes, whether it came from a hand-written
``capture.toml`` (the ``scene`` stage) or from photogrammetry (a later ``geometry`` stage).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from objcam.dr_memory import padded
from objcam.errors import InputError

MITSUBA_VARIANT_PREFERENCE = ("llvm_ad_rgb", "scalar_rgb")
# variants kept when already set (objcam.transport.variant sets cuda_ad_rgb on a GPU machine, process-wide)
MITSUBA_VARIANTS_KEPT = MITSUBA_VARIANT_PREFERENCE + ("cuda_ad_rgb",)


def use_mitsuba(variant: str | None = None):
    """Import Mitsuba with the fast LLVM variant (falls back to ``scalar_rgb``) and return the module; a variant
    already set among ``MITSUBA_VARIANTS_KEPT`` (the transport's choice, objcam.transport.variant) is kept."""
    import mitsuba as mi

    if variant is not None:
        mi.set_variant(variant)
        return mi
    if mi.variant() in MITSUBA_VARIANTS_KEPT:
        return mi
    last = None
    for v in MITSUBA_VARIANT_PREFERENCE:
        try:
            mi.set_variant(v)
            return mi
        except Exception as e:  # missing libLLVM: fall back
            last = e
    raise RuntimeError(f"no usable Mitsuba variant ({last}); run `make setup` (installs libllvm19)")


@dataclass
class MeshData:
    """A triangle mesh in world metres.

    vertices: (V, 3) float32 metres; faces: (F, 3) uint32; uv: (V, 2) float32 or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None

    def save(self, path: str | Path) -> None:
        from objcam.image_io import save_npz

        arrays = {"vertices": self.vertices, "faces": self.faces}
        if self.uv is not None:
            arrays["uv"] = self.uv
        save_npz(path, **arrays)

    @classmethod
    def load_npz(cls, path: str | Path) -> "MeshData":
        with np.load(path) as z:
            return cls(z["vertices"], z["faces"], z["uv"] if "uv" in z.files else None)

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


def load_mesh(path: str | Path) -> MeshData:
    """Load a PLY/OBJ/STL/OFF mesh with pymeshlab; a clear InputError if it cannot be used.

    Per-vertex UVs are kept when the file has them (per-wedge UVs are converted to per-vertex ones by
    splitting seams).
    """
    import pymeshlab

    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file not found", path, "check the path in capture.toml")
    from objcam.mesh_check import scan

    problem, declared = scan(path)
    if problem:  # the loader would drop these silently, or report them as an unreadable file
        raise InputError(f"mesh is malformed: {problem}", path, "repair or re-export the mesh")
    ms = pymeshlab.MeshSet()
    cwd = os.getcwd()
    try:
        ms.load_new_mesh(str(path))
    except Exception as e:  # pymeshlab raises PyMeshLabException with multi-line text
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(f"mesh does not load ({first})", path, "export it as PLY or OBJ") from None
    finally:  # a failed load leaves the process in the mesh's folder (pymeshlab 2023.12)
        os.chdir(cwd)
    m = ms.current_mesh()
    if declared and (m.vertex_number() < declared[0] or m.face_number() < declared[1]):
        raise InputError(f"mesh declares {declared[0]} vertices and {declared[1]} faces but only "
                         f"{m.vertex_number()} and {m.face_number()} load (NaN or infinite coordinates, or face "
                         "indices past the vertex list)", path, "repair or re-export the mesh")
    if m.face_number() == 0 or m.vertex_number() < 3:
        raise InputError("mesh has no triangles", path, "export the surface as a triangle mesh")
    uv = None
    if m.has_wedge_tex_coord() and not m.has_vertex_tex_coord():
        try:
            ms.apply_filter("compute_texcoord_transfer_wedge_to_vertex")
        except Exception:
            pass
        m = ms.current_mesh()
    if m.has_vertex_tex_coord():
        uv = np.asarray(m.vertex_tex_coord_matrix(), dtype=np.float32)
    v = np.asarray(m.vertex_matrix(), dtype=np.float32)
    f = np.asarray(m.face_matrix(), dtype=np.uint32)
    if not np.all(np.isfinite(v)):
        raise InputError("mesh has NaN or infinite vertex coordinates", path, "repair or re-export the mesh")
    return MeshData(v, f, uv)


def make_plane(size: float, texture_extent: float | None = None) -> MeshData:
    """The support plane z = 0: a square of side ``size`` metres centred on the origin, facing +z.

    UVs are chosen so that [0, 1]^2 covers a square of ``texture_extent`` metres centred on the origin (u along
    +x, v along -y so that image row 0 is at +y); outside it the texture is clamped.
    """
    h = size / 2.0
    v = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], dtype=np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
    e = texture_extent if texture_extent else size
    uv = np.stack([v[:, 0] / e + 0.5, 0.5 - v[:, 1] / e], axis=1).astype(np.float32)
    return MeshData(v, f, uv)


class AlbedoValue(BaseModel):
    """A resolved albedo: a constant RGB, or an EXR texture (path relative to the scene folder). Neither: unknown;
    ``initial`` then may name an estimate (photogrammetry's texture over the mesh's UVs) to start a joint solve,
    and ``uniform`` says the surface has one albedo per colour (capture.toml's ``"uniform"``), which the solve
    estimates as one value instead of one per pixel."""

    model_config = ConfigDict(extra="forbid")
    rgb: tuple[float, float, float] | None = None
    texture: str | None = None
    initial: str | None = None
    uniform: bool = False

    @property
    def known(self) -> bool:
        return self.rgb is not None or self.texture is not None


class SceneDescription(BaseModel):
    """What transport needs to know about the scene; written as ``scene.json`` beside its mesh files."""

    model_config = ConfigDict(extra="forbid")
    object_mesh: str  # npz relative to the scene folder
    support_mesh: str  # npz relative to the scene folder (the plane is a mesh too)
    support_is_plane: bool
    albedo_object: AlbedoValue
    albedo_support: AlbedoValue

    def albedo_is_grey(self) -> bool:
        """True when every known albedo is a grey constant and unknown ones are rendered as 1."""
        for a in (self.albedo_object, self.albedo_support):
            if a.texture is not None:
                return False
            if a.rgb is not None and not (a.rgb[0] == a.rgb[1] == a.rgb[2]):
                return False
        return True


def _bsdf(mi, albedo: AlbedoValue, root: Path, unknown_value: float, channel: int | None,
          initial: bool = False):
    texture = albedo.texture if albedo.texture is not None else (albedo.initial if initial else None)
    if texture is not None:
        from objcam.image_io import read_exr

        tex = read_exr(root / texture)[..., :3]
        if tex.shape[2] == 1:
            tex = np.repeat(tex, 3, axis=2)
        if channel is not None:
            tex = np.repeat(tex[..., channel : channel + 1], 3, axis=2)
        refl = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(tex, dtype=np.float32)),
                "raw": True, "wrap_mode": "clamp", "filter_type": "bilinear"}
    else:
        rgb = albedo.rgb if albedo.rgb is not None else (unknown_value,) * 3
        if channel is not None:
            rgb = (rgb[channel],) * 3
        refl = {"type": "rgb", "value": list(rgb)}
    return mi.load_dict({"type": "diffuse", "reflectance": refl})


def mitsuba_mesh(mi, name: str, mesh: MeshData, bsdf):
    """A Mitsuba mesh object built from numpy arrays (no file round trip)."""
    props = mi.Properties()
    props["bsdf"] = bsdf
    m = mi.Mesh(name, vertex_count=len(mesh.vertices), face_count=len(mesh.faces),
                has_vertex_normals=False, has_vertex_texcoords=mesh.uv is not None, props=props)
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(padded(mesh.vertices, np.float32).ravel())  # objcam.dr_memory
    p["faces"] = mi.UInt32(padded(mesh.faces, np.uint32).ravel())
    if mesh.uv is not None:
        p["vertex_texcoords"] = mi.Float(padded(mesh.uv, np.float32).ravel())
    p.update()
    return m


def build_mitsuba_scene(desc: SceneDescription, root: str | Path, envmap: np.ndarray | None = None,
                        unknown_albedo: float = 1.0, channel: int | None = None, extra: dict | None = None,
                        initial: bool = False):
    """The Mitsuba scene of ``desc`` (files relative to ``root``).

    envmap: optional (H, 2H, 3) radiance in objcam's lat-long convention, added as the ``envmap`` emitter.
    unknown_albedo: the albedo rendered where the description says it is unknown; with ``initial``, an unknown
    albedo's ``initial`` estimate (texture) where it has one.
    channel: if set, every albedo takes that colour channel's value (grey render of one channel).
    extra: more entries for the scene dict (sensor, integrator, extra shapes).
    """
    from objcam.envmap import mitsuba_envmap_to_world, to_mitsuba_bitmap

    mi = use_mitsuba()
    root = Path(root)
    obj = MeshData.load_npz(root / desc.object_mesh)
    sup = MeshData.load_npz(root / desc.support_mesh)
    d: dict = {"type": "scene"}
    d["object"] = mitsuba_mesh(mi, "object", obj, _bsdf(mi, desc.albedo_object, root, unknown_albedo, channel,
                                                        initial))
    d["support"] = mitsuba_mesh(mi, "support", sup, _bsdf(mi, desc.albedo_support, root, unknown_albedo, channel,
                                                          initial))
    if envmap is not None:
        d["emitter"] = {
            "type": "envmap",
            "bitmap": mi.Bitmap(to_mitsuba_bitmap(np.asarray(envmap, dtype=np.float32)[..., :3])),
            "to_world": mi.ScalarTransform4f(mitsuba_envmap_to_world().tolist()),
        }
    if extra:
        d.update(extra)
    return mi.load_dict(d)
