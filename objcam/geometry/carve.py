"""Silhouette carving into a signed field, coarse to fine, vectorised in numpy.

Each view contributes a signed distance to its silhouette's boundary (pixels, from distance transforms: positive
inside the object mask), converted to metres at the voxel's depth (x depth / fx). The field at a point is the
(k+1)-th smallest of these over the views that frame it (k = ``outlier_views``: a voxel survives being outside
k silhouettes, so k bad masks cannot dig a tunnel, at the price of a hull widened wherever fewer than k + 1 views
see a concavity; objcam.geometry.hull carves with k = 0 once the masks' doubtful pixels are marked). A view may
carry an outline offset image (objcam.geometry.outline) that is subtracted from its distances. The field's zero
level set is the visual hull, located to a fraction of a voxel (``objcam.geometry.surface`` interpolates it), so
voxels need not be tiny.

Coarse to fine: the field is evaluated on a coarse grid over the whole volume, the volume is cropped to the
cells the object may occupy, and each level halves the voxel and re-evaluates only the cells within a few
half-diagonals of the surface; the rest inherit their parent's value (its sign is certain there).

Below ``base_height`` the silhouettes cannot separate the object from the plane (no parallax; see
``objcam.geometry.silhouette``), so the hull's cross-section at that height is extruded down to z = 0; below
z = 0 the field is negative (the object ends on the support), which closes the mesh there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class CarveParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    voxel_size: float = Field(0.5e-3, gt=0, description="finest voxel side, metres")
    coarse_cells: int = Field(40, ge=8, le=512, description="cells along the volume's longest side at the "
                              "coarsest level")
    outlier_views: int = Field(0, ge=0, description="a point survives being outside this many silhouettes")
    base_height: float = Field(3e-3, ge=0, description="below this height (metres) the hull's cross-section "
                               "at this height is extruded down to z = 0")
    min_framed: float = Field(0.5, gt=0, le=1, description="a point framed by fewer than this fraction of the "
                              "views is outside (too little evidence to keep it)")
    band: float = Field(2.0, gt=0, description="cells within band x half-diagonal of the surface are refined")


@dataclass
class CarvedField:
    """values: (nx, ny, nz) float32 signed distance estimate, metres, positive inside; sample (i, j, k) sits at
    ``origin + voxel * (i, j, k)``. evaluated: how many (point, view) samples were computed."""

    values: np.ndarray
    origin: np.ndarray
    voxel: float
    evaluated: int

    def points(self, idx: np.ndarray) -> np.ndarray:
        return self.origin + self.voxel * np.asarray(idx, dtype=np.float64)

    @property
    def occupied_volume(self) -> float:
        return float((self.values > 0).sum()) * self.voxel**3


class _ViewField:
    """One view's signed distance image (pixels) and camera, sampled at world points."""

    def __init__(self, mask: np.ndarray, known: np.ndarray | None, cam, offset: np.ndarray | None = None):
        from objcam.geometry.maskfield import signed_distance

        self.unknown = None if known is None else (~known).astype(np.uint8)
        self.sd = signed_distance(mask)
        if offset is not None:  # the outline measured off the image (objcam.geometry.outline)
            self.sd -= offset
        cw = np.linalg.inv(cam.matrix)
        self.r, self.t = cw[:3, :3], cw[:3, 3]
        self.cam = cam

    def sample(self, x: np.ndarray) -> np.ndarray:
        """Signed distance (N,) metres of world points x (N, 3) to this silhouette; +inf outside the frame."""
        import cv2

        c = self.cam
        p = x @ self.r.T + self.t
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = c.fx * p[:, 0] / z + c.cx
            v = c.fy * p[:, 1] / z + c.cy
        framed = (z > 0) & (u >= 0) & (u <= c.width - 1) & (v >= 0) & (v <= c.height - 1)
        n = len(x)
        cols = 4096
        rows = -(-n // cols)
        mu = np.zeros(rows * cols, np.float32)
        mv = np.zeros(rows * cols, np.float32)
        mu[:n] = np.where(framed, u, 0)
        mv[:n] = np.where(framed, v, 0)
        mu, mv = mu.reshape(rows, cols), mv.reshape(rows, cols)
        sd = cv2.remap(self.sd, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()[:n]
        if self.unknown is not None:  # no evidence there: like outside the frame
            framed &= cv2.remap(self.unknown, mu, mv, cv2.INTER_NEAREST,
                                borderMode=cv2.BORDER_REPLICATE).ravel()[:n] == 0
        return np.where(framed, sd * z / c.fx, np.inf)


def _evaluate(fields: list[_ViewField], x: np.ndarray, k: int, min_framed: int,
              chunk: int = 400_000) -> np.ndarray:
    """The field at points x (N, 3): the (k+1)-th smallest view value; -1 m (outside) where fewer than
    ``min_framed`` views frame the point (the edges of the volume that few views see carry too little evidence)."""
    out = np.empty(len(x), np.float32)
    kk = min(k, len(fields) - 1)
    for s in range(0, len(x), chunk):
        xs = x[s:s + chunk]
        vals = np.stack([f.sample(xs) for f in fields])  # (V, n)
        framed = np.isfinite(vals).sum(axis=0)
        v = np.partition(vals, kk, axis=0)[kk]
        out[s:s + chunk] = np.where((framed >= min_framed) & np.isfinite(v), v, -1.0)
    return out


def _crop(vals: np.ndarray, origin: np.ndarray, h: float, band: float) -> tuple[np.ndarray, np.ndarray]:
    """The sub-grid holding every sample that may be inside (value above -band half-diagonals) plus one sample
    of margin."""
    occ = np.argwhere(vals > -band * h * np.sqrt(3) / 2)
    if len(occ) == 0:
        return vals, origin
    a = np.maximum(occ.min(axis=0) - 1, 0)
    b = np.minimum(occ.max(axis=0) + 2, vals.shape)
    return vals[a[0]:b[0], a[1]:b[1], a[2]:b[2]], origin + h * a


def carve(masks: list, cams: list, box_lo: np.ndarray, box_hi: np.ndarray,
          params: CarveParams | None = None) -> CarvedField:
    """The carved signed field inside the box [box_lo, box_hi] (metres; box_lo[2] is lowered to below z = 0).

    masks: per view an (H, W) bool mask (True = object), or a tuple (mask, known[, offset]) where ``known`` (H, W)
    bool says where the mask carries evidence (elsewhere the view is treated as not framing the point) and
    ``offset`` (H, W) float32 pixels how far the mask's outline lies outside the object's (objcam.geometry.outline).
    cams: the views' cameras (objcam Camera).
    """
    params = params or CarveParams()
    fields = []
    for m, c in zip(masks, cams):
        m = m if isinstance(m, tuple) else (m,)
        fields.append(_ViewField(m[0], m[1] if len(m) > 1 else None, c, m[2] if len(m) > 2 else None))
    k = params.outlier_views
    mf = max(1, int(np.ceil(params.min_framed * len(fields))))
    lo = np.asarray(box_lo, float).copy()
    hi = np.asarray(box_hi, float).copy()
    # the finest voxel times 2^levels is the coarse cell; choose levels so the coarse grid has ~coarse_cells
    n_levels = max(0, int(np.ceil(np.log2(max(hi - lo) / params.voxel_size / params.coarse_cells))))
    h0 = params.voxel_size * 2**n_levels
    lo[2] = -2 * h0  # samples under z = 0 (outside) close the mesh on the plane
    shape = np.maximum(np.ceil((hi - lo) / h0).astype(int) + 1, 2)
    evaluated = 0

    def fix_base(vals, origin, h):
        """Extrude the cross-section at base_height down to z = 0; outside below z = 0."""
        z = origin[2] + h * np.arange(vals.shape[2])
        above = np.nonzero(z >= params.base_height)[0]
        if len(above):
            kb = above[0]
            low = (z < z[kb]) & (z >= 0)
            vals[:, :, low] = vals[:, :, kb : kb + 1]
        below = z < 0
        vals[:, :, below] = np.minimum(vals[:, :, below], z[below].astype(np.float32))
        return vals

    # level 0: everything
    idx = np.indices(shape).reshape(3, -1).T
    vals = _evaluate(fields, lo + h0 * idx.astype(np.float64), k, mf).reshape(shape)
    evaluated += idx.shape[0] * len(fields)
    vals = fix_base(vals, lo, h0)
    origin = lo.copy()
    h = h0
    vals, origin = _crop(vals, origin, h, params.band)
    for _ in range(n_levels):
        # the finer lattice is origin + (h/2) * i: parent sample c sits at fine index 2c, and fine index 2c + 1
        # (between two parents) inherits parent c's value, which is within h/2 per axis of it
        near = np.abs(vals) < params.band * h * np.sqrt(3) / 2
        vals = np.repeat(np.repeat(np.repeat(vals, 2, 0), 2, 1), 2, 2)[:-1, :-1, :-1]
        near = np.repeat(np.repeat(np.repeat(near, 2, 0), 2, 1), 2, 2)[:-1, :-1, :-1]
        h = h / 2
        idx = np.argwhere(near)
        vals[near] = _evaluate(fields, origin + h * idx.astype(np.float64), k, mf)
        evaluated += len(idx) * len(fields)
        vals = fix_base(vals, origin, h)
        vals, origin = _crop(vals, origin, h, params.band)
    return CarvedField(vals.astype(np.float32), origin, h, evaluated)
