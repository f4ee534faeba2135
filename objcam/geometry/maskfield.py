"""A silhouette as a signed distance image: what carving and silhouette registration sample at projected points."""

from __future__ import annotations

import numpy as np


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 signed distance, pixels, from each pixel centre to the boundary of ``mask`` (H, W) bool:
    positive inside (True), negative outside; +-0.5 on the pixels either side of the boundary, so the zero level
    lies on the pixel edge between them."""
    import cv2

    m = np.asarray(mask).astype(np.uint8)
    d_in = cv2.distanceTransform(m, cv2.DIST_L2, 5)
    d_out = cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
    return np.where(m > 0, d_in - 0.5, 0.5 - d_out).astype(np.float32)


def bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``img`` (H, W) or (H, W, C) sampled bilinearly at pixel coordinates u (N,) (column), v (N,) (row),
    clamped to the image; returns (N,) or (N, C)."""
    h, w = img.shape[:2]
    u = np.clip(np.asarray(u, np.float64), 0, w - 1)
    v = np.clip(np.asarray(v, np.float64), 0, h - 1)
    u0 = np.minimum(np.floor(u).astype(np.int64), w - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), h - 2)
    a, b = u - u0, v - v0
    if img.ndim == 3:
        a, b = a[:, None], b[:, None]
    return ((1 - a) * (1 - b) * img[v0, u0] + a * (1 - b) * img[v0, u0 + 1]
            + (1 - a) * b * img[v0 + 1, u0] + a * b * img[v0 + 1, u0 + 1])
