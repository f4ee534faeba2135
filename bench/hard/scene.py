"""The suite's own Mitsuba scene: written from data_layout.md's text, never through objcam's scene builder,
transport or envmap module, so the targets cannot share the solver's assumptions.

- Camera: the capture's pinhole (OpenCV axes: x right, y down, z forward; principal point at the image centre)
  becomes Mitsuba's ``perspective`` sensor, whose local frame has x to the image's left and y up: so Mitsuba's
  to_world is world_from_camera with its x and y axes negated.
- Envmap: Mitsuba's ``envmap`` looks a local direction d up at u = atan2(d.x, -d.z) / 2 pi, v = acos(d.y) / pi
  (row 0 at local +y). The contract's texel (row r, column c) is the world direction of polar angle theta from +z
  and azimuth phi from +x towards +y. With local y = world +z, local x = world -y and local z = world -x,
  atan2(d.x, -d.z) = atan2(-sin phi, cos phi) = -phi: Mitsuba's u runs against phi, so the bitmap handed to it is
  the contract's with its columns reversed (a proper rotation needs no mirror). tests/test_bench_hard.py checks
  it: a lamp's shadow, found in the image through the contract's camera, points away from the lamp. Mitsuba
  interpolates the bitmap bilinearly between samples at polar angle pi i / (rows - 1), while the contract's row r
  is the box [pi r / H, pi (r + 1) / H]: :func:`render` hands it the map in box form (:func:`contract_bitmap`).
  Handed the H rows as they are, the sky is stretched towards the poles by up to half a texel: a lamp 5 deg from
  the zenith then lit the plane 4.8% less than its truth (session 21).
- Surfaces: two-sided diffuse, flat-shaded (face normals); the support a 20 m square at z = 0 (the contract's
  default plane).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

PLANE_SIZE = 20.0


def look_at_camera(elevation_deg: float, azimuth_deg: float, distance: float, target, size: int,
                   fov_deg: float = 45.0) -> dict:
    """The contract's camera JSON (dict) on a sphere of ``distance`` around ``target``, looking at it, image
    ``size`` x ``size``, horizontal field of view ``fov_deg``."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    tgt = np.asarray(target, float)
    eye = tgt + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    z = tgt - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])  # right: forward x up
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # down
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
    return {"width": size, "height": size, "fx": f, "fy": f, "cx": (size - 1) / 2, "cy": (size - 1) / 2,
            "world_from_camera": m.tolist()}


def overhead_camera(size: int, height: float, fov_deg: float = 60.0) -> dict:
    """A camera straight above the origin looking down: image x = world +x, image y (down) = world -y."""
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = [1, 0, 0], [0, -1, 0], [0, 0, -1], [0, 0, height]
    f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
    return {"width": size, "height": size, "fx": f, "fy": f, "cx": (size - 1) / 2, "cy": (size - 1) / 2,
            "world_from_camera": m.tolist()}


def envmap_to_world() -> np.ndarray:
    """4x4 to_world of Mitsuba's envmap for a column-reversed contract map (module docstring): local x -> world
    -y, local y -> world +z, local z -> world -x."""
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = [0, -1, 0], [0, 0, 1], [-1, 0, 0]
    return m


def contract_bitmap(env: np.ndarray, f: int = 2) -> np.ndarray:
    """(f H + 1, 2 f H, C) float32: the contract's map ``env`` (H, 2H, C) of box texels as the bitmap whose
    bilinear interpolation Mitsuba's envmap evaluates (samples at theta = pi i / (f H), column centres): each
    sample the texel it lies in, a sample on a row boundary the mean of the two texels (the zenith and nadir
    samples their own row's). The interpolated radiance then ramps between neighbours over 1/f of a texel,
    symmetrically about each boundary, so every texel emits its box's power and direction up to the ramps'
    second order; f = 8 is bench.gi_reference's one-hot texel."""
    h = env.shape[0]
    i = np.arange(f * h + 1)
    above, below = np.clip((i - 1) // f, 0, h - 1), np.clip(i // f, 0, h - 1)
    on_boundary = (i % f == 0).reshape(-1, *([1] * (env.ndim - 1)))
    rows = np.where(on_boundary, 0.5 * (env[above] + env[below]), env[below])
    return np.repeat(rows, f, axis=1).astype(np.float32)


def _diffuse(albedo: float) -> dict:
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [albedo] * 3}}}


def scene_dict(mesh: Path, camera: dict, envmap: np.ndarray, albedo_object: float, albedo_support: float,
               spp: int, seed: int, max_depth: int) -> dict:
    """The Mitsuba scene (a dict for ``mi.load_dict``): path tracer of ``max_depth``, the camera, the envmap
    bitmap (rows sampled at theta = pi i / (rows - 1), columns in the contract's order: :func:`contract_bitmap` of
    a contract map), the object mesh (PLY, world metres) and the support plane."""
    import mitsuba as mi

    w, h = camera["width"], camera["height"]
    if abs(camera["cx"] - (w - 1) / 2) > 1e-6 or abs(camera["cy"] - (h - 1) / 2) > 1e-6:
        raise ValueError("principal point off the image centre: not supported by this writer")
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # OpenCV (x right, y down) -> Mitsuba (x left, y up)
    to_world = np.asarray(camera["world_from_camera"], float) @ flip
    fov = math.degrees(2 * math.atan((w / 2) / camera["fx"]))
    bitmap = mi.Bitmap(np.ascontiguousarray(envmap[:, ::-1].astype(np.float32)))
    plane = mi.ScalarTransform4f().scale([PLANE_SIZE / 2, PLANE_SIZE / 2, 1.0])  # rectangle: [-1, 1]^2, normal +z
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth)},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f(to_world.tolist()),
                   "near_clip": 1e-3, "far_clip": 100.0,
                   "film": {"type": "hdrfilm", "width": w, "height": h, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "multijitter", "sample_count": int(spp), "seed": int(seed)}},
        "light": {"type": "envmap", "bitmap": bitmap, "to_world": mi.ScalarTransform4f(envmap_to_world().tolist())},
        # face normals: the object is the mesh as given (Mitsuba would otherwise interpolate vertex normals, which
        # turns a box's corners into diagonals and shades its faces like a rounded object)
        "object": {"type": "ply", "filename": str(mesh), "face_normals": True, "bsdf": _diffuse(albedo_object)},
        "support": {"type": "rectangle", "to_world": plane, "bsdf": _diffuse(albedo_support)},
    }


def render(mesh: Path, camera: dict, envmap: np.ndarray, albedo_object: float, albedo_support: float,
           spp: int, seed: int, max_depth: int = 4) -> tuple[np.ndarray, float]:
    """Path-trace the scene: (image (h, w, 3) float32 linear radiance, relative Monte Carlo noise per pixel at the
    median pixel, :func:`median_pixel_noise`). A multi-jittered sampler (measured 5-7x less noise than independent
    samples at 512 spp on a lamp and a sun). Rendered as two halves of ``spp / 2`` samples with different seeds;
    their difference measures the render's own noise."""
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb")
    bitmap = contract_bitmap(envmap)  # the contract's box texels, not Mitsuba's sample rows (module docstring)
    halves = []
    for k in range(2):
        scene = mi.load_dict(scene_dict(mesh, camera, bitmap, albedo_object, albedo_support,
                                        max(spp // 2, 1), seed * 2 + k, max_depth))
        halves.append(np.asarray(mi.render(scene), dtype=np.float64)[..., :3])
    a, b = halves
    img = 0.5 * (a + b)
    return img.astype(np.float32), median_pixel_noise(img, 0.5 * (a - b))


#: pixels "at the median": brightness within this factor of the median pixel's, either way
NEAR_MEDIAN = 1.25


def median_pixel_noise(img: np.ndarray, half_diff: np.ndarray) -> float:
    """The render's relative Monte Carlo noise at the median pixel: the standard deviation of the two halves' mean
    (``half_diff`` = (a - b) / 2, (h, w, 3)) over the pixels whose brightness (channel mean of ``img``) lies within
    NEAR_MEDIAN of the median pixel's, over the median positive value of ``img`` (the camera noise's reference,
    bench.hard.capture.add_noise); the whole image's when fewer than 100 pixels are that near. Not the whole
    image's deviation (RENDER_VERSION v3 and before): a light object's fireflies made that 5-25x the median pixel's
    (lamp3_r251 on the light bunny seen from 60 deg: 3.9% against 0.35%), and capture.toml's noise_sigma with it."""
    pos = img[img > 0]
    med = float(np.median(pos)) if pos.size else 1.0
    lum = img.mean(axis=-1)
    lpos = lum[lum > 0]
    near = np.zeros(lum.shape, bool)
    if lpos.size:
        ratio = np.maximum(lum, 1e-300) / float(np.median(lpos))
        near = (ratio < NEAR_MEDIAN) & (ratio > 1.0 / NEAR_MEDIAN)
    d = half_diff[near] if near.sum() >= 100 else half_diff
    return float(np.std(d) / med)
