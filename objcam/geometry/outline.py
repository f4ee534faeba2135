"""Sub-pixel outlines: where a silhouette mask's edge lies off the image's own edge, measured along the outline.

The plane-parallax masks (objcam.geometry.silhouette) mark a pixel object when it differs from the plane by more
than a tolerance, so a pixel that the object covers only partly is marked when its coverage times the contrast
exceeds that tolerance: against a contrasting background the mask runs ~0.5-1 px outside the object (measured:
median offset 0 px at relative contrast below 0.2, 0.4 px at 0.2-0.4, 0.6-1.0 px above), where it hardly matters
at low contrast. A visual hull from such masks is too fat by as much.

The image itself says where the edge is: along the outline's normal the radiance goes from the object's level to
the background's, and the pixel-integrated edge crosses their mean where the object covers half the pixel, i.e. at
the true edge. :func:`outline_offset` measures, at every boundary pixel with enough contrast, the distance from the
mask's edge to that crossing, smooths it along the outline, and returns it as an image that carving subtracts
from the mask's signed distance.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class OutlineParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(True, description="move each mask's outline onto the image's edge where the contrast "
                          "allows")
    min_contrast: float = Field(0.2, ge=0, description="relative contrast across the outline needed to measure it")
    reach_px: float = Field(3.0, gt=1, description="object and background levels are read this far either side")
    max_offset_px: float = Field(1.5, gt=0, description="larger measured offsets are not trusted (other edges)")
    smooth_px: float = Field(3.0, gt=0, description="offsets are averaged along the outline over this scale")
    blur_px: float = Field(0.6, ge=0, description="Gaussian blur of the image before reading profiles (noise)")


def outline_offset(image: np.ndarray, mask: np.ndarray, params: OutlineParams | None = None) -> np.ndarray:
    """(H, W) float32 pixels to subtract from the signed distance of ``mask`` (H, W) bool: near the outline, how
    far the mask's edge lies outside the object's edge in ``image`` (H, W, 3) linear RGB (negative: inside),
    averaged along the outline; 0 elsewhere and along stretches too low in contrast to measure."""
    import cv2

    from objcam.geometry.maskfield import bilinear, signed_distance

    params = params or OutlineParams()
    h, w = mask.shape
    grey = np.asarray(image, np.float32)[..., :3].mean(axis=2)
    if params.blur_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), params.blur_px)
    floor = 0.05 * float(np.median(grey))
    m8 = mask.astype(np.uint8)
    sd = signed_distance(mask)
    gy, gx = np.gradient(cv2.GaussianBlur(sd, (0, 0), 1.0))
    # boundary pixels on the object side (4-neighbourhood)
    inner = mask & ~cv2.erode(m8, cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))).astype(bool)
    ys, xs = np.nonzero(inner)
    out = np.zeros((h, w), np.float32)
    if len(ys) == 0:
        return out
    n = np.stack([-gx[ys, xs], -gy[ys, xs]], axis=1)  # outward: sd decreases outward
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    r = params.reach_px
    s = np.arange(-r, r + 1e-9, 0.25)  # (S,) positions along the normal, pixels
    px = xs[:, None] + s[None, :] * n[:, :1]
    py = ys[:, None] + s[None, :] * n[:, 1:]
    prof = bilinear(grey, px.ravel(), py.ravel()).reshape(len(ys), len(s))
    ends = max(1, int(round(1.0 / 0.25)))  # the last pixel's worth of samples at each end
    obj = np.median(prof[:, :ends], axis=1)
    bg = np.median(prof[:, -ends:], axis=1)
    contrast = np.abs(obj - bg) / (0.5 * (obj + bg) + floor)
    # the crossing of the mid level nearest the pixel: sign changes of (profile - mid), linearly interpolated
    f = (prof - 0.5 * (obj + bg)[:, None]) * np.sign(obj - bg)[:, None]  # positive on the object side
    change = (f[:, :-1] > 0) & (f[:, 1:] <= 0)
    t = f[:, :-1] / np.where(change, f[:, :-1] - f[:, 1:], 1.0)
    cross = np.where(change, s[None, :-1] + t * (s[1] - s[0]), np.inf)
    best = cross[np.arange(len(ys)), np.argmin(np.abs(cross), axis=1)]
    # the mask's edge along the normal: where its signed distance (sd at the pixel) runs out
    offset = sd[ys, xs] - best
    ok = np.isfinite(best) & (contrast >= params.min_contrast) & (np.abs(offset) <= params.max_offset_px)
    num = np.zeros((h, w), np.float32)
    num[ys[ok], xs[ok]] = offset[ok]
    # average along the outline over all its pixels (unmeasured ones count as 0: no correction there), spread to
    # the band around it
    num = cv2.GaussianBlur(num, (0, 0), params.smooth_px)
    band = cv2.GaussianBlur(inner.astype(np.float32), (0, 0), params.smooth_px)
    return np.where(band > 1e-3, num / np.maximum(band, 1e-6), 0.0).astype(np.float32)
