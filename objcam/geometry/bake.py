"""Bake the linear views onto surface points: per point, the robust radiance over the views that see it.

A sample is used when the point is in front of the camera and inside its frame, the surface faces the camera
(cosine above ``min_cos``: grazing views smear the texture), and nothing occludes it (a Mitsuba ray test from the
point towards the camera centre against the object and support meshes). The baked value is the per-channel
median of the accepted samples; the spread (median absolute deviation / median) and the count give a
confidence.

What the robust statistic can and cannot remove: for a diffuse surface, radiance is the same from every view,
so the median rejects what differs between views -- occlusion edges misplaced by geometry error, highlights,
mis-segmented pixels. A cast shadow is the same in every view under one illumination: it cannot be told from
darker albedo here and stays baked in (the joint solve, which knows the light, is what can separate them).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.geometry.raycast import RayScene
from objcam.geometry.views import View


class BakeParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    min_cos: float = Field(0.2, ge=0, lt=1, description="least cosine between the normal and the view direction")
    offset: float = Field(2e-4, gt=0, description="ray origin offset along the normal, metres (self-hits)")
    full_count: int = Field(4, ge=1, description="samples for full confidence")


class Baked(BaseModel):
    """Per point: radiance (N, 3) median, count (N,), spread (N,) relative MAD, confidence (N,) in [0, 1];
    and how many candidate samples each test rejected."""

    model_config = ConfigDict(arbitrary_types_allowed=True)
    radiance: np.ndarray
    count: np.ndarray
    spread: np.ndarray
    confidence: np.ndarray
    rejected: dict[str, int]


def bake(points: np.ndarray, normals: np.ndarray, views: list[View], rays: RayScene,
         params: BakeParams | None = None, progress: bool = True) -> Baked:
    """Bake ``views`` onto ``points`` (N, 3) world metres with unit ``normals`` (N, 3)."""
    import cv2

    from objcam.progress import bar

    params = params or BakeParams()
    n = len(points)
    samples = np.full((len(views), n, 3), np.nan, np.float32)
    rejected = {"out_of_frame": 0, "facing_away": 0, "occluded": 0, "saturated": 0}
    it = bar(range(len(views)), total=len(views), desc="bake", unit="view") if progress else range(len(views))
    for k in it:
        v = views[k]
        cam = v.camera
        to_cam = cam.centre - points
        dist = np.linalg.norm(to_cam, axis=1)
        d = to_cam / np.maximum(dist[:, None], 1e-12)
        uv = cam.project(points)
        cw = np.linalg.inv(cam.matrix)
        depth = points @ cw[2, :3] + cw[2, 3]
        framed = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & \
                 (uv[:, 1] <= cam.height - 1)
        facing = np.einsum("ij,ij->i", normals, d) > params.min_cos
        cand = framed & facing
        rejected["out_of_frame"] += int((~framed).sum())
        rejected["facing_away"] += int((framed & ~facing).sum())
        idx = np.nonzero(cand)[0]
        if len(idx) == 0:
            continue
        o = points[idx] + params.offset * normals[idx]
        occ = rays.occluded(o, d[idx], dist[idx] - 2 * params.offset)
        rejected["occluded"] += int(occ.sum())
        idx = idx[~occ]
        cols = 4096
        m = len(idx)
        r = -(-m // cols)
        mu = np.zeros(r * cols, np.float32)
        mv = np.zeros(r * cols, np.float32)
        mu[:m], mv[:m] = uv[idx, 0], uv[idx, 1]
        val = cv2.remap(v.image, mu.reshape(r, cols), mv.reshape(r, cols), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:m]
        if v.valid is not None:  # saturated pixels (ingest's views_valid) are no measurement of radiance
            ok = cv2.remap(v.valid.astype(np.uint8), mu.reshape(r, cols), mv.reshape(r, cols), cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0).ravel()[:m] > 0
            rejected["saturated"] += int((~ok).sum())
            idx, val = idx[ok], val[ok]
        samples[k, idx] = val
    count = np.isfinite(samples[..., 0]).sum(axis=0)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN texels: unseen, handled below
            med = np.nanmedian(samples, axis=0)
            lum = samples.mean(axis=2)
            mlum = np.nanmedian(lum, axis=0)
            mad = np.nanmedian(np.abs(lum - mlum), axis=0)
    spread = np.where(count > 0, mad / np.maximum(mlum, 1e-12), np.inf)
    med = np.where(count[:, None] > 0, med, 0.0).astype(np.float32)
    # confidence: enough views, and views that agree (a spread of 50% or more is no estimate)
    conf = np.minimum(count / params.full_count, 1.0) * np.clip(1.0 - 2.0 * np.nan_to_num(spread, posinf=1.0), 0, 1)
    return Baked(radiance=med, count=count.astype(np.int32), spread=np.nan_to_num(spread, posinf=0).astype(np.float32),
                 confidence=conf.astype(np.float32), rejected=rejected)
