"""Which background pixels of the silhouettes could as well be object: the plane-parallax test
(objcam.geometry.silhouette) calls a pixel background when the plane behind it looks the same from the other views,
which is also true of an object part that happens to look like that plane (its lit top against white paper, its
shaded flank against its own shadow). One such view carves the part away.

The object is diffuse: a point of it has the same radiance in every view that sees it. So for a pixel that a first,
robust hull (carved tolerating a few wrong views) says is object but the mask says is background, the hull's
surface point behind it is projected into the other views that see it unoccluded and call it object; when the
pixel's value matches theirs (median), the object explains it as well as the plane does and the pixel carries no
evidence either way: it is marked unknown, and carving no longer cuts there. Pixels the object cannot explain stay
background, so true background inside a too generous hull is still carved.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.scene import MeshData


class AmbiguityParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(True, description="mark background pixels the object would explain as unknown, and carve "
                          "again")
    robust_outliers: int = Field(2, ge=0, description="the first hull tolerates this many wrong views per point")
    tolerance: float = Field(0.1, gt=0, description="relative radiance difference still counted as the object's")
    min_support: int = Field(2, ge=1, description="views that must see the hull point as object to predict it")
    blur_px: float = Field(1.0, ge=0, description="Gaussian blur of the images before comparing, pixels")
    dark_floor: float = Field(0.05, ge=0, description="added to the denominator, as a fraction of the view's median")


def ambiguous_background(images: list[np.ndarray], masks: list, cams: list, hull: MeshData,
                         params: AmbiguityParams | None = None) -> list[np.ndarray]:
    """Per view an (H, W) bool map of the background pixels the object explains as well (see the module).

    images: the views' linear images (H, W, 3); masks: per view (mask, known) (H, W) bool; cams: their cameras;
    hull: a robust visual hull (world metres), a superset of the object where the masks erred."""
    import cv2

    from objcam.geometry.maskfield import bilinear
    from objcam.geometry.raycast import RayScene

    params = params or AmbiguityParams()
    rays = RayScene([hull])
    blurred = [cv2.GaussianBlur(np.asarray(im, np.float32), (0, 0), params.blur_px) if params.blur_px > 0
            else np.asarray(im, np.float32) for im in images]
    floors = [params.dark_floor * float(np.median(g.mean(axis=2))) for g in blurred]
    cws = [np.linalg.inv(c.matrix) for c in cams]
    hv = np.asarray(hull.vertices, np.float64)
    out = []
    for i, (cam, (mask, known)) in enumerate(zip(cams, masks)):
        amb = np.zeros(mask.shape, bool)
        # candidate pixels: background with evidence, within the hull's projected bounding box
        uv = cam.project(hv)
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 2, [cam.width, cam.height])
        vv, uu = np.nonzero(~mask[v0:v1, u0:u1] & known[v0:v1, u0:u1])
        if len(uu) == 0:
            out.append(amb)
            continue
        uu, vv = uu + u0, vv + v0
        o, d = cam.rays(uu.astype(np.float64), vv.astype(np.float64))
        t = rays.hit_distance(o, d)
        hit = np.isfinite(t)
        uu, vv, o, d, t = uu[hit], vv[hit], o[hit], d[hit], t[hit]
        x = o + t[:, None] * d  # the hull's surface point behind each pixel
        vals = np.full((len(cams), len(x), 3), np.nan, np.float32)
        for j, cj in enumerate(cams):
            if j == i:
                continue
            pc = x @ cws[j][:3, :3].T + cws[j][:3, 3]
            z = pc[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = cj.fx * pc[:, 0] / z + cj.cx
                v = cj.fy * pc[:, 1] / z + cj.cy
            ok = (z > 0) & (u >= 0) & (u <= cj.width - 1) & (v >= 0) & (v <= cj.height - 1)
            if not ok.any():
                continue
            iu, iv = np.rint(u[ok]).astype(int), np.rint(v[ok]).astype(int)
            mj, kj = masks[j]
            ok[ok] = mj[iv, iu] & kj[iv, iu]
            if not ok.any():
                continue
            # seen unoccluded from view j: nothing of the hull between the point (lifted off it) and the camera
            to_c = cj.centre - x[ok]
            dist = np.linalg.norm(to_c, axis=1)
            eps = 2.0 * dist / cj.fx  # two pixels' footprint: off the hull's own surface
            start = x[ok] + (eps / dist)[:, None] * to_c
            seen = ~rays.occluded(start, to_c, dist - eps)
            idx = np.nonzero(ok)[0][seen]
            vals[j, idx] = bilinear(blurred[j], u[idx], v[idx])
        n = np.isfinite(vals[..., 0]).sum(axis=0)
        pred = np.nanmedian(np.where(n[None, :, None] >= params.min_support, vals, 0.0), axis=0)
        obs = blurred[i][vv, uu]
        rel = np.abs(obs - pred).max(axis=1) / (0.5 * (obs + pred).mean(axis=1) + floors[i])
        expl = (n >= params.min_support) & (rel < params.tolerance)
        amb[vv[expl], uu[expl]] = True
        out.append(amb)
    return out
