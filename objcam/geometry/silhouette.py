"""Object silhouettes from plane-induced parallax: what is on the support plane looks the same from every view.

For view i, every other view j is warped onto it through the homography of the plane z = 0. A pixel that sees
the plane (paper, printed board, and the cast shadows: all on the plane, diffuse, under one illumination) finds
the same radiance in every view j that also sees that plane point; a pixel that sees the object does not,
except by chance. A pixel is **background** when at least ``agree_fraction`` of the views that frame its plane
point agree with it within ``tolerance``; everything else is object.

Why this and not appearance alone: the object can be as bright as the paper and as dark as its own shadow, and
the shadows move with the illumination; the plane's multi-view consistency needs no model of either. Why a
fraction of all views rather than a few neighbours: on a textureless object, a nearby view warped by a small
parallax shows a neighbouring patch of the same shade (the aperture problem) and agrees; views far around the
ring see the plane behind the object, or its other side, and disagree. Plane points near the object are hidden
by it from some views, at most about half of them, hence a fraction below one half.

What it cannot see: object points within about a pixel's parallax of the plane (the lowest millimetres) look
like the plane from every view. Carving handles that band (objcam.geometry.carve: ``base_height``).
The masks are generous by design: carving removes a voxel when any view calls it background, so a missed
object pixel digs a tunnel while a false object pixel is cut away by the other views. Their outline runs up to a
pixel outside the object's where the contrast is high (a partly covered pixel differs from the plane by its
coverage times the contrast); objcam.geometry.outline measures that off the image. Where the object looks like
the plane behind it (its lit top against white paper), the mask misses it; objcam.geometry.ambiguity finds such
pixels by the object's own consistency across views.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.geometry.views import View


class SilhouetteParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    tolerance: float = Field(0.03, gt=0, description="relative radiance difference still counted as agreement")
    agree_fraction: float = Field(0.34, gt=0, lt=1, description="fraction of views framing a plane point that "
                                  "must agree for the pixel to be background")
    min_views: int = Field(3, ge=1, description="a pixel framed by fewer other views stays object (no evidence)")
    blur_px: float = Field(0.8, ge=0, description="Gaussian blur before comparing (noise, resampling), pixels")
    dark_floor: float = Field(0.2, ge=0, description="added to the denominator, as a fraction of the view's median "
                              "level: differences between dark pixels (ink, deep shadow) are mostly noise")
    noise_factor: float = Field(0.0, ge=0, description="per pair of views the tolerance is at least this many "
                                "times the median difference (mostly noise: most pixels see the plane)")
    max_views: int = Field(24, ge=2, description="compare with at most this many other views (spread in angle)")
    close_px: int = Field(2, ge=0, description="morphological closing radius of the object mask, pixels")


def plane_homography(src, dst) -> np.ndarray:
    """3x3 homography taking pixels of camera ``src`` to pixels of camera ``dst`` through the plane z = 0."""
    def plane_to_pixels(cam) -> np.ndarray:
        cw = np.linalg.inv(cam.matrix)
        return cam.K @ np.c_[cw[:3, 0], cw[:3, 1], cw[:3, 3]]  # (x, y, 1) on z = 0 -> homogeneous pixel

    return plane_to_pixels(dst) @ np.linalg.inv(plane_to_pixels(src))


def _plane_points(cam, roi: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """World points (h, w, 3) where each pixel's ray meets z = 0, and whether it does (in front of the camera), for
    the pixels of ``roi`` (u0, v0, u1, v1)."""
    u0, v0, u1, v1 = roi
    vv, uu = np.mgrid[v0:v1, u0:u1].astype(np.float64)
    o, d = cam.rays(uu, vv)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[..., 2] / d[..., 2]
    ok = np.isfinite(t) & (t > 0)
    return o + np.where(ok, t, 0)[..., None] * d, ok


def volume_roi(cam, lo: np.ndarray, hi: np.ndarray, grow: float = 0.1) -> tuple[int, int, int, int]:
    """The pixels (u0, v0, u1, v1) (half-open) where the box [lo, hi] (world metres), grown by ``grow`` of its size
    on every side (carving samples a little beyond it), projects; the whole frame when a corner is behind the
    camera. Only these pixels' silhouettes are ever sampled."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pad = grow * (hi - lo)
    c = np.array(np.meshgrid(*zip(lo - pad, hi + pad), indexing="ij")).reshape(3, -1).T
    cw = np.linalg.inv(cam.matrix)
    if np.any(c @ cw[2, :3] + cw[2, 3] <= 0):
        return 0, 0, cam.width, cam.height
    uv = cam.project(c)
    u0, v0 = np.clip(np.floor(uv.min(axis=0)).astype(int) - 2, 0, [cam.width, cam.height])
    u1, v1 = np.clip(np.ceil(uv.max(axis=0)).astype(int) + 3, 0, [cam.width, cam.height])
    return int(u0), int(v0), int(u1), int(v1)


def _pick_others(views: list[View], i: int, k: int) -> list[int]:
    """Up to ``k`` other views spread evenly over the ring (sorted by optical-axis angle, then subsampled)."""
    z = np.array([v.camera.matrix[:3, 2] for v in views])
    ang = np.arccos(np.clip(z @ z[i], -1, 1))
    order = [j for j in np.argsort(ang) if j != i]
    if len(order) <= k:
        return order
    return [order[int(round(s))] for s in np.linspace(0, len(order) - 1, k)]


def silhouette(views: list[View], i: int, params: SilhouetteParams | None = None,
               blurred: list[np.ndarray] | None = None,
               roi: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """View ``i``'s object mask (H, W) bool (True = object), where it is known (H, W) bool (its plane point is
    framed by at least ``min_views`` other views; elsewhere there is no evidence either way) and the agreement
    fraction (H, W) float32. Only the pixels of ``roi`` (u0, v0, u1, v1) are decided (default: all); the rest are
    not known."""
    import cv2

    params = params or SilhouetteParams()
    if blurred is None:
        blurred = [_blur(v.image, params.blur_px) for v in views]
    cam = views[i].camera
    full_h, full_w = cam.height, cam.width
    u0, v0, u1, v1 = roi or (0, 0, full_w, full_h)
    h, w = v1 - v0, u1 - u0
    # a floor on the denominator so that dark noise does not count as disagreement
    floor = params.dark_floor * float(np.median(blurred[i].mean(axis=2)))
    ref = np.ascontiguousarray(blurred[i][v0:v1, u0:u1])
    q, on_plane = _plane_points(cam, (u0, v0, u1, v1))
    crop = np.array([[1.0, 0, u0], [0, 1, v0], [0, 0, 1]])  # ROI pixel -> pixel of view i
    agree = np.zeros((h, w), np.float32)
    framed = np.zeros((h, w), np.float32)
    kernel = np.ones((3, 3), np.uint8)
    ref_lo, ref_hi = cv2.erode(ref, kernel), cv2.dilate(ref, kernel)
    for j in _pick_others(views, i, params.max_views):
        cj = views[j].camera
        hom = plane_homography(cam, cj) @ crop  # ROI pixel of i -> pixel of j
        warped = cv2.warpPerspective(blurred[j], hom, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        inside = cv2.warpPerspective(np.ones((cj.height, cj.width), np.uint8), hom, (w, h),
                                     flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0) > 0
        # the homography also maps points behind camera j into its frame: require positive depth there
        cw = np.linalg.inv(cj.matrix)
        depth = q @ cw[2, :3] + cw[2, 3]
        ok = inside & on_plane & (depth > 0)
        if not ok.any():
            continue
        # sampling-insensitive dissimilarity (Birchfield-Tomasi): how far each value lies outside the other
        # image's 3x3 range, and the larger of the two ways. Edges of the print then agree despite sub-pixel
        # misregistration and the different resampling blur of the two views. Not the smaller of the two ways
        # (the usual symmetric form): the object seen where the other view shows an edge of the print lies
        # within that edge's range, and whole patches of the object agreed (measured: 8% of object pixels
        # missed, against 2% with the larger)
        w_lo, w_hi = cv2.erode(warped, kernel), cv2.dilate(warped, kernel)
        d1 = np.maximum(np.maximum(w_lo - ref, ref - w_hi), 0).max(axis=2)
        d2 = np.maximum(np.maximum(ref_lo - warped, warped - ref_hi), 0).max(axis=2)
        diff = np.maximum(d1, d2) / (0.5 * (warped.mean(axis=2) + ref.mean(axis=2)) + floor)
        tol = max(params.tolerance, params.noise_factor * float(np.median(diff[ok])))
        framed += ok
        agree += ok & (diff < tol)
    frac = np.where(framed > 0, agree / np.maximum(framed, 1), 0.0).astype(np.float32)
    background = (framed >= params.min_views) & (frac >= params.agree_fraction)
    obj = ~background
    # speckle of disagreement on the plane (noise, edges of the print) is removed by an opening; holes inside the
    # object (patches of the same shade matched by chance) are closed and filled
    obj8 = obj.astype(np.uint8)
    obj8 = cv2.morphologyEx(obj8, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
    if params.close_px > 0:
        r = params.close_px
        obj8 = cv2.morphologyEx(obj8, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                                                 (2 * r + 1, 2 * r + 1)))
    out = np.zeros((3, full_h, full_w), np.float32)
    out[:, v0:v1, u0:u1] = fill_holes(obj8 > 0), framed >= params.min_views, frac
    return out[0] > 0, out[1] > 0, out[2]


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with its enclosed background regions (not connected to the image border) set."""
    import cv2

    h, w = mask.shape
    pad = np.zeros((h + 2, w + 2), np.uint8)
    pad[1:-1, 1:-1] = mask
    flood = pad.copy()
    ff = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(flood, ff, (0, 0), 1)
    return (mask | (flood[1:-1, 1:-1] == 0)).astype(bool)


def silhouettes(views: list[View], params: SilhouetteParams | None = None, progress: bool = True,
                rois: list | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(object mask, known) (H, W) bool of every view (see :func:`silhouette`), within each view's ROI
    (:func:`volume_roi`; default: the whole frame)."""
    from objcam.progress import bar

    params = params or SilhouetteParams()
    blurred = [_blur(v.image, params.blur_px) for v in views]
    it = range(len(views))
    if progress:
        it = bar(it, total=len(views), desc="silhouettes", unit="view")
    rois = rois or [None] * len(views)
    return [silhouette(views, i, params, blurred, rois[i])[:2] for i in it]

