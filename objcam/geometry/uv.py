"""UV atlases (xatlas) and their rasterisation: which surface point each texel centre is.

Texture convention (objcam.scene.make_plane, Mitsuba's bitmap): texel (row r, column c) of an (R, C) image sits
at uv = ((c + 0.5) / C, (r + 0.5) / R): u along columns, v along rows, row 0 at v = 0.
"""

from __future__ import annotations

import numpy as np

from objcam.scene import MeshData


def atlas(mesh: MeshData, resolution: int, padding: int = 2) -> MeshData:
    """``mesh`` with an xatlas UV atlas packed for a ``resolution``^2 texture (vertices split along seams)."""
    return atlas_sized(mesh, resolution=resolution, padding=padding)[0]


def atlas_sized(mesh: MeshData, texels_per_unit: float = 0.0, resolution: int = 0,
                padding: int = 2) -> tuple[MeshData, tuple[int, int], float]:
    """An xatlas UV atlas of ``mesh`` at ``texels_per_unit`` texels per metre (0: fitted to ``resolution``) packed
    into a ``resolution``^2 texture (0: as large as the density needs). Returns the mesh (vertices split along
    seams, faces in the same order), the texture's (rows, columns) and the texels per metre achieved."""
    import xatlas

    at = xatlas.Atlas()
    at.add_mesh(np.ascontiguousarray(mesh.vertices, np.float32), np.ascontiguousarray(mesh.faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.texels_per_unit = float(texels_per_unit)
    pack.padding = int(padding)
    pack.bilinear = True  # leave room for bilinear lookups at chart borders
    at.generate(xatlas.ChartOptions(), pack)
    vmap, faces, uv = at[0]
    out = MeshData(np.ascontiguousarray(mesh.vertices[vmap], np.float32), faces.astype(np.uint32),
                   uv.astype(np.float32))
    return out, (int(at.height), int(at.width)), float(at.texels_per_unit)


def rasterize(mesh: MeshData, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Texel -> surface point of a UV-mapped mesh.

    Returns face (R, C) int64 (-1 where no triangle covers the texel centre) and barycentrics (R, C, 3).
    Triangles are drawn in uv space with cv2.fillConvexPoly (sub-pixel shift), then barycentrics are computed
    exactly at texel centres; texels a triangle's fill touched but whose centre lies slightly outside keep the
    clamped barycentrics (they are gutter texels, sampled by bilinear lookups).
    """
    import cv2

    rows, cols = size
    uv = np.asarray(mesh.uv, np.float64) * np.array([cols, rows]) - 0.5  # texel-centre pixel coordinates
    f = np.asarray(mesh.faces, np.int64)
    ids = np.full((rows, cols), -1, np.int32)
    shift = 4
    pts = np.round(uv[f] * (1 << shift)).astype(np.int32)
    for k in range(len(f)):  # ~10 us a triangle
        cv2.fillConvexPoly(ids, pts[k], int(k), lineType=cv2.LINE_8, shift=shift)
    rr, cc = np.nonzero(ids >= 0)
    fk = ids[rr, cc].astype(np.int64)
    a, b, c = uv[f[fk, 0]], uv[f[fk, 1]], uv[f[fk, 2]]
    p = np.stack([cc, rr], 1).astype(np.float64)
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) < 1e-12, 1e-12, den)
    w1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    w2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    bary = np.clip(np.stack([1 - w1 - w2, w1, w2], 1), 0, 1)
    bary /= bary.sum(axis=1, keepdims=True)
    out_b = np.zeros((rows, cols, 3))
    out_b[rr, cc] = bary
    return ids.astype(np.int64), out_b


def surface_points(mesh: MeshData, face: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) and unit face normals (N, 3) of the covered texels (face >= 0), in row-major order."""
    sel = face >= 0
    fk = face[sel]
    v = np.asarray(mesh.vertices, np.float64)
    tri = v[np.asarray(mesh.faces, np.int64)[fk]]
    pts = np.einsum("nk,nkd->nd", bary[sel], tri)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return pts, n


def fill_gutter(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``image`` (R, C, ...) with invalid texels set to their nearest valid texel's value (so bilinear lookups at
    chart borders and unseen texels read plausible values)."""
    from scipy.ndimage import distance_transform_edt

    if valid.all() or not valid.any():
        return image
    _, (ri, ci) = distance_transform_edt(~valid, return_indices=True)
    return image[ri, ci]
