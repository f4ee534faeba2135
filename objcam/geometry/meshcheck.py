"""Checks of a known object mesh before the geometry stage spends minutes on it (issue 4's bad input)."""

from __future__ import annotations

import numpy as np

from objcam.errors import InputError
from objcam.scene import MeshData


def edge_face_counts(faces: np.ndarray) -> np.ndarray:
    """How many faces share each distinct undirected edge of ``faces`` (F, 3): (E,) counts."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key = e[:, 0] * (int(f.max()) + 1) + e[:, 1]
    return np.unique(key, return_counts=True)[1]


def check_known_mesh(mesh: MeshData, path=None) -> None:
    """Raise InputError (one line) when ``mesh`` cannot be the surface of a solid object: no triangles, zero area,
    or non-manifold edges (shared by more than two faces: a broken export or several shells glued together).
    Open borders (holes) are accepted: registration and rendering do not need a closed surface."""
    faces = np.asarray(mesh.faces)
    if len(faces) == 0 or len(mesh.vertices) < 3:
        raise InputError("object mesh is empty (no triangles)", path, "export the object's surface as a triangle mesh")
    v = np.asarray(mesh.vertices, np.float64)
    if int(faces.max()) >= len(v):
        raise InputError("object mesh has faces that name missing vertices", path, "re-export the mesh")
    tri = v[faces.astype(np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    if not area > 0:
        raise InputError("object mesh has zero surface area", path, "export the object's surface")
    counts = edge_face_counts(faces)
    bad = int((counts > 2).sum())
    if bad:
        raise InputError(f"object mesh is not manifold: {bad} of {len(counts)} edges are shared by more than two "
                         "faces", path, "repair it (MeshLab: Filters > Cleaning and Repairing > Repair non Manifold "
                         "Edges) or export one closed shell")
