"""Where a sphere's silhouette falls in the image: the cone from the camera centre tangent to the ball
(:func:`objcam.probe.optics.silhouette_rays`), projected through an OpenCV pinhole camera.

Shared by the ball fit (:mod:`objcam.probe.fit`: detection scores, how far the rim model moves the silhouette),
the rim model (:mod:`objcam.probe.rim`: the band of pixels it fits) and the drawings of the fitted ball; its
own module so that those depend on it, not on each other.
"""

from __future__ import annotations

import numpy as np

from objcam.camera import Camera
from objcam.probe.optics import silhouette_rays


def silhouette_px(cam: Camera, centres: np.ndarray, radius: float, k: int) -> np.ndarray:
    """(..., k, 2) image points of the silhouettes of spheres at ``centres`` (..., 3) (NaN behind the camera)."""
    psi = 2 * np.pi * np.arange(k) / k
    o = cam.centre
    rays = silhouette_rays(centres, radius, o, psi)
    cam_from_world = np.linalg.inv(cam.matrix)
    p = rays @ cam_from_world[:3, :3].T  # directions in the camera frame
    z = np.where(p[..., 2] > 1e-9, p[..., 2], np.nan)
    return np.stack([cam.fx * p[..., 0] / z + cam.cx, cam.fy * p[..., 1] / z + cam.cy], -1)
