"""Cameras for other tools: a COLMAP text model and a nerfstudio-style ``transforms.json``.

objcam's cameras are OpenCV pinholes (x right, y down, z forward; pixel centres at integers) with a rigid
``world_from_camera`` in world metres, z up.

- COLMAP (``cameras.txt``, ``images.txt``, an empty ``points3D.txt``): model PINHOLE, params fx fy cx cy with
  COLMAP's pixel centres at +0.5 (cx_colmap = cx + 0.5); each image's pose is camera-from-world, the rotation as
  a unit quaternion (qw, qx, qy, qz) and the translation t = -R c.
- nerfstudio: ``transform_matrix`` is camera-to-world in OpenGL's camera axes (x right, y up, z backwards), i.e.
  world_from_camera @ diag(1, -1, -1, 1); intrinsics per frame (fl_x, fl_y, cx, cy, w, h) with cx, cy in COLMAP's
  pixel convention (nerfstudio's colmap converter copies COLMAP's values).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.image_io import atomic_write_text

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a proper rotation matrix (Shepperd's method: stable everywhere)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R)
    cand = [tr, R[0, 0], R[1, 1], R[2, 2]]
    k = int(np.argmax(cand))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def _g(x: float) -> str:
    return repr(float(x))  # shortest text that reads back to the same double


def write_colmap_text(folder: Path, cameras: dict[str, Camera], image_names: dict[str, str]) -> list[Path]:
    """``cameras.txt``, ``images.txt``, ``points3D.txt`` in ``folder``: one COLMAP camera and one image per entry
    of ``cameras`` (name -> Camera); ``image_names`` maps each to the image file the model names."""
    folder.mkdir(parents=True, exist_ok=True)
    cams = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            f"# Number of cameras: {len(cameras)}"]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(cameras)}, mean observations per image: 0"]
    for i, (name, cam) in enumerate(cameras.items(), start=1):
        cams.append(" ".join([str(i), "PINHOLE", str(cam.width), str(cam.height), _g(cam.fx), _g(cam.fy),
                              _g(cam.cx + 0.5), _g(cam.cy + 0.5)]))
        m = np.asarray(cam.world_from_camera, np.float64)
        R = m[:3, :3].T  # camera from world
        t = -R @ m[:3, 3]
        q = quaternion_from_rotation(R)
        imgs.append(" ".join([str(i), *map(_g, q), *map(_g, t), str(i), image_names[name]]))
        imgs.append("")
    paths = [folder / "cameras.txt", folder / "images.txt", folder / "points3D.txt"]
    atomic_write_text(paths[0], "\n".join(cams) + "\n")
    atomic_write_text(paths[1], "\n".join(imgs) + "\n")
    atomic_write_text(paths[2], "# 3D point list (empty: objcam exports cameras only)\n")
    return paths


def write_transforms_json(path: Path, cameras: dict[str, Camera], image_names: dict[str, str]) -> Path:
    """A nerfstudio-style ``transforms.json`` (module docstring) with one frame per camera."""
    frames = []
    for name, cam in cameras.items():
        c2w = np.asarray(cam.world_from_camera, np.float64) @ OPENGL_FROM_OPENCV
        frames.append({"file_path": image_names[name], "name": name, "camera_model": "OPENCV",
                       "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx + 0.5, "cy": cam.cy + 0.5,
                       "w": cam.width, "h": cam.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                       "transform_matrix": c2w.tolist()})
    doc = {"camera_model": "OPENCV", "orientation_override": "none", "applied_transform": np.eye(4)[:3].tolist(),
           "objcam": "world metres, z up; cx, cy in COLMAP's pixel convention (objcam's + 0.5)", "frames": frames}
    atomic_write_text(path, json.dumps(doc, indent=2))
    return path


def read_transforms_json(path: Path) -> dict[str, Camera]:
    """The cameras of a file written by :func:`write_transforms_json` (objcam's OpenCV convention)."""
    out = {}
    for f in json.loads(Path(path).read_text())["frames"]:
        m = np.asarray(f["transform_matrix"], np.float64) @ OPENGL_FROM_OPENCV
        out[f["name"]] = Camera(width=f["w"], height=f["h"], fx=f["fl_x"], fy=f["fl_y"], cx=f["cx"] - 0.5,
                                cy=f["cy"] - 0.5, world_from_camera=m.tolist())
    return out
