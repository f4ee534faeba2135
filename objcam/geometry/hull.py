"""The visual hull from the views' silhouettes, in two passes: a robust one to learn which background pixels could
be object, and the final, tight one.

1. Outlines (objcam.geometry.outline): each mask's edge is moved onto the image's edge where the contrast allows.
2. A robust hull: carved tolerating ``ambiguity.robust_outliers`` wrong views per point, so parts that a few
   masks missed (the object's lit top against white paper) survive.
3. Ambiguity (objcam.geometry.ambiguity): background pixels inside that hull whose value the object explains as
   well as the plane are marked unknown.
4. The final hull: carved with those pixels unknown, tolerating ``carve.outlier_views`` (default 0: every view
   that is sure cuts; each tolerated view widens the hull wherever that view alone saw the object's concavity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from objcam.geometry.carve import CarvedField
from objcam.scene import MeshData


@dataclass
class Hull:
    """mesh: the hull (MeshData, world metres, resting on z = 0); field: its CarvedField; masks: per view the
    (mask, known, offset) it was carved from (known without the ambiguous pixels); stats: numbers for the
    stage's record."""

    mesh: MeshData
    field: CarvedField
    masks: list
    stats: dict


def _mesh(field, meshing) -> MeshData:
    from objcam.geometry.surface import clean_mesh, rest_on_plane, surface_nets

    raw = surface_nets(field.values, field.origin, field.voxel)
    if len(raw.faces) == 0:
        return raw
    return rest_on_plane(clean_mesh(raw, meshing))


def build_hull(images: list[np.ndarray], masks: list, cams: list, lo: np.ndarray, hi: np.ndarray, carve_params,
               outline_params, ambiguity_params, meshing) -> Hull:
    """The hull of the views (images (H, W, 3) linear, masks (mask, known) (H, W) bool, cameras) inside the box
    [lo, hi] (metres), by the steps in the module docstring. Returns an empty mesh when nothing is carved."""
    from objcam.geometry.ambiguity import ambiguous_background
    from objcam.geometry.carve import carve
    from objcam.geometry.outline import outline_offset

    stats: dict = {}
    if outline_params.enabled:
        offsets = [outline_offset(im, m, outline_params) for im, (m, _) in zip(images, masks)]
        moved = np.concatenate([o[o != 0] for o in offsets]) if offsets else np.zeros(0)
        stats["outline_offset_px"] = float(moved.mean()) if len(moved) else 0.0
    else:
        offsets = [None] * len(masks)
    tri = [(m, k, o) for (m, k), o in zip(masks, offsets)]
    if ambiguity_params.enabled:
        robust = carve(tri, cams, lo, hi, carve_params.model_copy(
            update={"outlier_views": ambiguity_params.robust_outliers}))
        first = _mesh(robust, meshing)
        if len(first.faces):
            amb = ambiguous_background(images, masks, cams, first, ambiguity_params)
            tri = [(m, k & ~a, o) for (m, k, o), a in zip(tri, amb)]
            stats["ambiguous_pixels"] = int(sum(int(a.sum()) for a in amb))
    field = carve(tri, cams, lo, hi, carve_params)
    return Hull(_mesh(field, meshing), field, tri, stats)
