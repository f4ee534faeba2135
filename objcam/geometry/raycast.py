"""Ray queries against meshes with Mitsuba (millions of rays a second on the CPU): occlusion and hit distance.

Used for texture visibility (is a surface point seen by a view?) and for true object masks in synthetic tests.
"""

from __future__ import annotations

import numpy as np

from objcam.dr_memory import padded
from objcam.scene import MeshData


class RayScene:
    """A Mitsuba scene made of ``meshes`` (world metres), for ray tests only (no emitter, no materials)."""

    def __init__(self, meshes: list[MeshData]):
        from objcam.scene import mitsuba_mesh, use_mitsuba

        self.mi = mi = use_mitsuba()
        d: dict = {"type": "scene"}
        bsdf = mi.load_dict({"type": "diffuse"})
        for k, m in enumerate(meshes):
            d[f"mesh{k}"] = mitsuba_mesh(mi, f"mesh{k}", MeshData(m.vertices, m.faces), bsdf)
        self.scene = mi.load_dict(d)

    def _rays(self, origins: np.ndarray, directions: np.ndarray, maxt: np.ndarray | float | None):
        mi = self.mi
        o = np.ascontiguousarray(np.reshape(origins, (-1, 3)), dtype=np.float32)
        dd = np.asarray(np.reshape(directions, (-1, 3)), dtype=np.float64)
        dd = np.ascontiguousarray(dd / np.linalg.norm(dd, axis=1, keepdims=True), dtype=np.float32)
        ray = mi.Ray3f(mi.Point3f(*(mi.Float(padded(o[:, i])) for i in range(3))),  # objcam.dr_memory
                       mi.Vector3f(*(mi.Float(padded(dd[:, i])) for i in range(3))))
        if maxt is not None:
            ray.maxt = mi.Float(padded(np.broadcast_to(maxt, (len(o),)), np.float32))
        return ray

    def occluded(self, origins: np.ndarray, directions: np.ndarray, maxt: np.ndarray | float | None = None,
                 chunk: int = 4_000_000) -> np.ndarray:
        """(N,) bool: whether the ray from each origin along its direction hits a mesh before ``maxt`` metres."""
        origins = np.reshape(origins, (-1, 3))
        directions = np.reshape(directions, (-1, 3))
        out = np.zeros(len(origins), dtype=bool)
        for s in range(0, len(origins), chunk):
            mt = None if maxt is None else np.broadcast_to(maxt, (len(origins),))[s:s + chunk]
            out[s:s + chunk] = np.asarray(self.scene.ray_test(self._rays(origins[s:s + chunk],
                                                                         directions[s:s + chunk], mt)))
        return out

    def hit_distance(self, origins: np.ndarray, directions: np.ndarray, chunk: int = 4_000_000) -> np.ndarray:
        """(N,) distance to the first hit along each ray, inf where nothing is hit."""
        origins = np.reshape(origins, (-1, 3))
        directions = np.reshape(directions, (-1, 3))
        out = np.full(len(origins), np.inf, dtype=np.float64)
        for s in range(0, len(origins), chunk):
            si = self.scene.ray_intersect(self._rays(origins[s:s + chunk], directions[s:s + chunk], None))
            t = np.asarray(si.t, dtype=np.float64)
            out[s:s + chunk] = np.where(np.asarray(si.is_valid()), t, np.inf)
        return out


def object_masks(obj: MeshData, cams: list) -> list[np.ndarray]:
    """True object masks (H, W) bool: pixels whose centre ray meets the object before the plane z = 0."""
    rs = RayScene([obj])
    out = []
    for cam in cams:
        vv, uu = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
        o, d = cam.rays(uu, vv)
        t_obj = rs.hit_distance(o.reshape(-1, 3), d.reshape(-1, 3))
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = -o[..., 2].ravel() / d[..., 2].ravel()
        t_plane = np.where(t_plane > 0, t_plane, np.inf)
        out.append((t_obj < t_plane).reshape(cam.height, cam.width))
    return out
