"""Distances between meshes: area-uniform surface samples and nearest neighbours (scipy's cKDTree)."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict

from objcam.scene import MeshData


class ChamferResult(BaseModel):
    """Distances in metres. ``mean`` = (a_to_b + b_to_a) / 2, each the mean nearest-surface distance of one mesh's
    samples to the other's; ``p95`` the larger of the two 95th percentiles."""

    model_config = ConfigDict(frozen=True)
    mean: float
    a_to_b: float
    b_to_a: float
    p95: float


def sample_surface(mesh: MeshData, n: int, seed: int = 0, with_normals: bool = False):
    """``n`` points (n, 3) uniformly by area on the mesh (and their face normals (n, 3) if asked)."""
    rng = np.random.default_rng(seed)
    v = np.asarray(mesh.vertices, np.float64)
    tri = v[np.asarray(mesh.faces, np.int64)]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    pts = np.einsum("nk,nkd->nd", w, tri[face])
    if not with_normals:
        return pts
    nrm = cross[face] / np.maximum(np.linalg.norm(cross[face], axis=1, keepdims=True), 1e-30)
    return pts, nrm


def point_to_surface(points: np.ndarray, mesh: MeshData, n_samples: int = 200_000, seed: int = 1) -> np.ndarray:
    """Approximate distance (N,) from each point to the mesh surface (nearest of ``n_samples`` surface samples;
    the sampling adds about half the samples' spacing)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(sample_surface(mesh, n_samples, seed))
    return tree.query(np.asarray(points, np.float64), workers=1)[0]


def chamfer(a: MeshData, b: MeshData, n: int = 100_000, seed: int = 0) -> ChamferResult:
    """Symmetric Chamfer distance between two meshes from ``n`` area-uniform samples on each (densely sampled
    targets: 4n points, so the sampling itself adds little)."""
    pa = sample_surface(a, n, seed)
    pb = sample_surface(b, n, seed + 1)
    dab = point_to_surface(pa, b, 4 * n, seed + 2)
    dba = point_to_surface(pb, a, 4 * n, seed + 3)
    return ChamferResult(mean=float(0.5 * (dab.mean() + dba.mean())), a_to_b=float(dab.mean()),
                         b_to_a=float(dba.mean()), p95=float(max(np.percentile(dab, 95), np.percentile(dba, 95))))
