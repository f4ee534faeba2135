"""The registered views, as the geometry and texture stages read them from the ingest and sfm artifacts.

Contract (objcam/stages/ingest.py, objcam/stages/sfm.py): ``ingest/views.json`` lists the views;
``ingest/views/<stem>.exr`` is linear RGB; ``sfm/cameras/views/<stem>.json`` is its camera (absent when SfM did not
register the view); ``sfm/points.npz`` holds the sparse points (world metres).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.errors import InputError


@dataclass
class View:
    """One registered view: ``image`` (H, W, 3) float32 linear RGB, its ``camera`` (same size), and ``valid``
    (H, W) bool (ingest's views_valid/<stem>.png: not saturated, inside the undistorted frame) or None (all)."""

    name: str
    image: np.ndarray
    camera: Camera
    valid: np.ndarray | None = None


def load_views(ingest: Path, sfm: Path, min_views: int = 4) -> list[View]:
    """Every view that has both a linear image and a camera, in views.json order.

    Raises InputError (one line) when views.json is missing or unreadable, an image's size differs from its
    camera's, or fewer than ``min_views`` views are registered.
    """
    from objcam.image_io import read_exr

    index = Path(ingest) / "views.json"
    try:
        records = json.loads(index.read_text())
    except FileNotFoundError:
        raise InputError("views.json not found", index, "run the ingest stage first") from None
    except json.JSONDecodeError as e:
        raise InputError(f"views.json is not valid JSON ({e.msg})", index, "rerun the ingest stage") from None
    views = []
    for rec in records:
        name = rec["name"]
        cam_path = Path(sfm) / "cameras" / "views" / f"{name}.json"
        if not cam_path.is_file():
            continue  # not registered by SfM
        cam = Camera.load(cam_path)
        img_path = Path(ingest) / "views" / f"{name}.exr"
        try:
            img = read_exr(img_path)
        except Exception as e:
            raise InputError(f"view image does not read ({type(e).__name__})", img_path,
                             "rerun the ingest stage") from None
        img = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
        if img.shape[:2] != (cam.height, cam.width):
            raise InputError(f"view is {img.shape[1]}x{img.shape[0]} but its camera says {cam.width}x{cam.height}",
                             img_path, "rerun ingest and sfm so that cameras match the view copies")
        valid = None
        vpath = Path(ingest) / "views_valid" / f"{name}.png"
        if vpath.is_file():
            import cv2

            m = cv2.imread(str(vpath), cv2.IMREAD_UNCHANGED)
            if m is not None and m.shape[:2] == img.shape[:2]:
                valid = m.reshape(m.shape[0], m.shape[1], -1)[..., 0] > 127
        views.append(View(name, np.ascontiguousarray(np.maximum(np.nan_to_num(img), 0.0), np.float32), cam, valid))
    if len(views) < min_views:
        raise InputError(f"only {len(views)}/{len(records)} views are registered; geometry needs at least "
                         f"{min_views}", Path(sfm) / "cameras" / "views",
                         "take more overlapping views all around the object and rerun sfm")
    return views


def load_points(sfm: Path) -> np.ndarray:
    """(P, 3) float64 sparse points, world metres (empty when sfm wrote none)."""
    path = Path(sfm) / "points.npz"
    if not path.is_file():
        return np.zeros((0, 3))
    with np.load(path) as z:
        return np.asarray(z["xyz"], dtype=np.float64).reshape(-1, 3)


def view_direction_angles(views: list[View]) -> np.ndarray:
    """(N, N) angle in radians between the views' optical axes (for picking neighbours)."""
    z = np.array([v.camera.matrix[:3, 2] for v in views])
    return np.arccos(np.clip(z @ z.T, -1.0, 1.0))
