"""The scene as transport sees it: the Mitsuba scene, which shape is which, and the surface points that the
camera's sub-pixel samples land on (primary rays)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.dr_memory import padded
from objcam.scene import MeshData, SceneDescription, build_mitsuba_scene, use_mitsuba
from objcam.transport.pixels import subpixel_positions


_UNPICKLED: dict = {}  # the last scene rebuilt by unpickling (objcam.transport.shards' workers)


@dataclass
class SceneGeometry:
    """The Mitsuba scene of a scene artifact plus the facts the direct model's culling needs.

    plane: the support is the rectangle [x0, x1] x [y0, y1] of the plane z = 0 (checked, not trusted from
    support_is_plane); then upward rays from above it never hit it.
    """

    desc: SceneDescription
    root: Path
    mi_scene: object
    object_mesh: MeshData
    support_mesh: MeshData
    object_id: int
    support_id: int
    plane: tuple[float, float, float, float] | None
    eps: float  # shadow-ray origin offset along the normal, metres
    env_height: int = 8  # of the envmap emitter (path renders)
    upsample: int = 8  # of its box bitmap (objcam.render.mitsuba_box_bitmap)

    def __getstate__(self) -> dict:
        # pickled as what loads it (a Dask worker rebuilds the Mitsuba scene from the shared scene artifact; the
        # shape ids are this process's pointers, so they are found again there)
        return {"desc": self.desc, "root": self.root, "env_height": self.env_height, "upsample": self.upsample}

    def __setstate__(self, state: dict) -> None:
        import mitsuba as mi

        # one scene per worker for every model pickled from it (direct blocks, then the gather's chunks)
        root, desc = Path(state["root"]), state["desc"]
        files = tuple((st.st_size, st.st_mtime_ns) for st in (os.stat(root / f) for f in
                                                                 (desc.object_mesh, desc.support_mesh)))
        # a long-lived worker may see the same path rebuilt by a later run: the files' stat is in the key
        key = (desc.model_dump_json(), str(root), files, state["env_height"], state["upsample"], mi.variant())
        if key not in _UNPICKLED:
            _UNPICKLED.clear()
            _UNPICKLED[key] = SceneGeometry.load(state["desc"], state["root"], state["env_height"], state["upsample"])
        self.__dict__.update(_UNPICKLED[key].__dict__)

    @classmethod
    def load(cls, desc: SceneDescription, root: str | Path, env_height: int = 8, upsample: int = 8) -> "SceneGeometry":
        """Build the Mitsuba scene (with an envmap emitter holding one lit texel, for path renders; ``upsample``:
        of its box bitmap, whose bilinear ramps at texel boundaries are 1/upsample texel wide)."""
        import drjit as dr

        from objcam.render import mitsuba_box_bitmap

        mi = use_mitsuba()
        root = Path(root)
        env = np.zeros((env_height, 2 * env_height, 3), np.float32)
        env[0, 0] = 1.0
        scene = build_mitsuba_scene(desc, root, envmap=mitsuba_box_bitmap(env, upsample), unknown_albedo=1.0)
        ids = {}
        for s in scene.shapes():
            ids[s.id()] = int(np.asarray(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s)))[0])
        obj = MeshData.load_npz(root / desc.object_mesh)
        sup = MeshData.load_npz(root / desc.support_mesh)
        lo, hi = obj.bbox
        diag = float(np.linalg.norm(hi - lo))
        extent = float(max(np.abs(obj.vertices).max(), np.abs(sup.vertices).max()))
        eps = max(1e-4 * diag, 4e-6 * extent, 1e-7)
        return cls(desc, root, scene, obj, sup, ids["object"], ids["support"], _plane_rectangle(sup, desc), eps,
                   int(env_height), int(upsample))


def _plane_rectangle(mesh: MeshData, desc: SceneDescription) -> tuple[float, float, float, float] | None:
    """(x0, x1, y0, y1) when the support mesh is a filled axis-aligned rectangle in z = 0, else None."""
    if not desc.support_is_plane:
        return None
    v = mesh.vertices.astype(np.float64)
    if np.abs(v[:, 2]).max() > 1e-7 * max(1.0, np.abs(v).max()):
        return None
    tri = v[mesh.faces.astype(np.int64)]
    area = 0.5 * np.abs(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]).sum()
    x0, y0 = v[:, 0].min(), v[:, 1].min()
    x1, y1 = v[:, 0].max(), v[:, 1].max()
    box = (x1 - x0) * (y1 - y0)
    if box <= 0 or abs(area - box) > 1e-5 * box:  # holes or overlaps: treat it as a general mesh
        return None
    return float(x0), float(x1), float(y0), float(y1)


@dataclass
class PixelSamples:
    """K camera samples for each of M pooled pixels (all arrays (M, K, ...)).

    hit: the sample's ray meets a surface. pos: the hit point pushed off the surface by eps along ``normal``,
    which faces the camera. rho: the albedo rendered there (unknown albedo rendered as 1; 0 where no hit).
    on_object / unknown: which surface, and whether its albedo is unknown. ray_dir: the camera ray direction
    (what a sample that misses sees of the envmap).
    """

    pixel_index: np.ndarray  # (M,) flat index into the pooled image
    hit: np.ndarray
    pos: np.ndarray
    normal: np.ndarray
    rho: np.ndarray
    on_object: np.ndarray
    unknown: np.ndarray
    ray_dir: np.ndarray

    @property
    def k(self) -> int:
        return self.hit.shape[1]

    def subset(self, keep: np.ndarray) -> "PixelSamples":
        return PixelSamples(*(getattr(self, f)[keep] for f in
                              ("pixel_index", "hit", "pos", "normal", "rho", "on_object", "unknown", "ray_dir")))

    # per-pixel summaries ------------------------------------------------------------------------------------
    def coverage(self) -> np.ndarray:
        """(M,) fraction of samples that hit a surface."""
        return self.hit.mean(axis=1).astype(np.float32)

    def albedo(self) -> np.ndarray:
        """(M, 3) mean rendered albedo over the samples that hit."""
        n = np.maximum(self.hit.sum(axis=1), 1)[:, None]
        return (self.rho.sum(axis=1) / n).astype(np.float32)

    def unknown_albedo(self) -> np.ndarray:
        """(M,) True where any sample lands on a surface of unknown albedo."""
        return (self.unknown & self.hit).any(axis=1)

    def object_fraction(self) -> np.ndarray:
        """(M,) fraction of the hitting samples that land on the object."""
        n = np.maximum(self.hit.sum(axis=1), 1)
        return ((self.on_object & self.hit).sum(axis=1) / n).astype(np.float32)


def primary_samples(geo: SceneGeometry, camera: Camera, f: int, k: int, pixel_index: np.ndarray,
                    pooled_width: int, seed: int) -> PixelSamples:
    """Trace K primary rays per pooled pixel (stratified over its f x f footprint, fixed seed)."""
    import drjit as dr

    mi = use_mitsuba()
    rng = np.random.default_rng([int(seed), 0x51D0])
    pix = np.asarray(pixel_index, dtype=np.int64)
    m = pix.size
    u, v = subpixel_positions(pix, pooled_width, f, k, rng)
    o, d = camera.rays(u.ravel(), v.ravel())
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(*(padded(o32[:, i]) for i in range(3))),  # objcam.dr_memory
                   mi.Vector3f(*(padded(d32[:, i]) for i in range(3))))
    si = geo.mi_scene.ray_intersect(ray)
    valid = si.is_valid()
    rho = si.bsdf().eval_diffuse_reflectance(si, valid)
    shape = dr.reinterpret_array(mi.UInt32, si.shape)
    dr.eval(si.p, si.n, rho, valid, shape)
    hit = np.asarray(valid, dtype=bool)
    p = np.asarray(si.p, dtype=np.float64).T.copy()
    n = np.asarray(si.n, dtype=np.float64).T.copy()
    r = np.asarray(rho, dtype=np.float64).T.copy()
    sid = np.asarray(shape, dtype=np.int64)
    # the normal faces the camera (robust to the mesh's winding)
    flip = np.sum(n * d, axis=1) > 0
    n[flip] *= -1.0
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    pos = p + geo.eps * n
    on_obj = hit & (sid == geo.object_id)
    on_sup = hit & (sid == geo.support_id)
    unknown = (on_obj & (not geo.desc.albedo_object.known)) | (on_sup & (not geo.desc.albedo_support.known))
    pos[~hit] = 0.0
    n[~hit] = 0.0
    r[~hit] = 0.0
    shp = (m, k)
    return PixelSamples(pix, hit.reshape(shp), pos.reshape(shp + (3,)), n.reshape(shp + (3,)),
                        r.reshape(shp + (3,)), on_obj.reshape(shp), unknown.reshape(shp), d.reshape(shp + (3,)))


@dataclass
class SampleParts:
    """The kept pixels' samples as disjoint parts, each a PixelSamples with its own sample count (the object's
    pixels get more: objcam.transport.build). ``rows`` of a part are positions into ``pixel_index``."""

    pixel_index: np.ndarray  # (M,)
    parts: list  # [(rows (M_part,), PixelSamples)]

    @classmethod
    def single(cls, s: PixelSamples) -> "SampleParts":
        return cls(s.pixel_index, [(np.arange(s.pixel_index.size), s)])

    def _scatter(self, name: str) -> np.ndarray:
        first = getattr(self.parts[0][1], name)()
        out = np.zeros((self.pixel_index.size,) + first.shape[1:], first.dtype)
        for rows, s in self.parts:
            out[rows] = getattr(s, name)()
        return out

    def coverage(self) -> np.ndarray:
        return self._scatter("coverage")

    def albedo(self) -> np.ndarray:
        return self._scatter("albedo")

    def unknown_albedo(self) -> np.ndarray:
        return self._scatter("unknown_albedo")

    def object_fraction(self) -> np.ndarray:
        return self._scatter("object_fraction")
