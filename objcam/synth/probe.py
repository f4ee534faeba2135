"""Synthetic chrome-ball captures: a smooth conductor sphere under a bundled (or given) envmap, path-traced
through an objcam camera, turned into an exposure bracket (scale, camera noise, clip at the white level) and
merged with :func:`objcam.capture.hdr.merge_frames`.

The envmap is emitted as box texels (:func:`objcam.render.mitsuba_box_bitmap`, ``upsample`` 16 by default: its
ramps at texel boundaries are 1/16 texel wide; at 4 they moved enough of a bright texel's energy into its
neighbours to raise the probe's per-texel RMSE at 32 x 64 from 0.059 to 0.076 on forest at 1024 px), so the truth
at any coarser resolution is ``area_downsample(envmap, h)``. No support plane is rendered by default: the ball floats
with its centre at z = radius (where it would rest on z = 0), so the whole sphere of directions is the envmap;
``plane_albedo`` adds a diffuse plane z = 0 (then the lower hemisphere the ball sees is that plane, not the map).

Ball materials: ``"Cr"`` (or any Mitsuba conductor name): physical Fresnel; the matching unwrap model is
``Reflectance(reflectance=None, fresnel="conductor", eta, k)`` with the conductor's RGB eta/k, returned in
:attr:`ProbeRender.reflectance`. ``"mirror"``: Mitsuba's ``conductor`` with ``material="none"`` (reflectance 1 at
every angle) scaled by ``mirror_reflectance``; the matching model is ``Reflectance(mirror_reflectance, "none")``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from objcam.camera import Camera, look_at
from objcam.probe.optics import Reflectance


@dataclass
class ProbeRender:
    clean: np.ndarray  # (H, W, 3) float32 noise-free radiance (scene units)
    camera: Camera
    centre: np.ndarray  # (3,) true ball centre, world metres
    radius: float
    envmap: np.ndarray  # (h, 2h, 3) the envmap rendered (box texels), objcam convention
    reflectance: Reflectance  # the unwrap model matching the rendered material
    spp: int
    seconds: float


@dataclass
class ProbeBracket:
    frames: list  # LinearImage per frame, white-level units (1.0 = clip)
    times: list[float]  # exposure times, seconds
    merge: object  # objcam.capture.hdr.MergeResult
    hdr: np.ndarray  # merged radiance converted back to scene units (radiance / scale)
    scale: float  # merged radiance = scene radiance * scale


def probe_camera(centre: np.ndarray, radius: float, distance: float = 0.35, elevation_deg: float = 25.0,
                 azimuth_deg: float = 0.0, size: int | tuple[int, int] = 256, ball_px: float = 150.0,
                 offset_px: tuple[float, float] = (0.0, 0.0)) -> Camera:
    """A camera at ``distance`` (metres, centre to centre) from the ball, seen from ``elevation_deg`` above the
    horizontal at azimuth ``azimuth_deg`` (from +x towards +y), focal length such that the ball's apparent
    diameter is about ``ball_px`` pixels; ``offset_px`` (du, dv) turns the camera so the ball lands that far from
    the image centre (off-axis: its image is then an ellipse)."""
    w, h = (size, size) if isinstance(size, int) else size
    c = np.asarray(centre, np.float64)
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    eye = c + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    alpha = np.arcsin(radius / distance)
    f = 0.5 * ball_px / np.tan(alpha)
    m = look_at(eye, c)
    du, dv = offset_px
    if du or dv:  # aim at a point beside the ball so that it projects about (du, dv) off centre
        target = c - distance * (du / f) * m[:3, 0] - distance * (dv / f) * m[:3, 1]
        m = look_at(eye, target)
    return Camera(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2, world_from_camera=m.tolist())


def _scene(mi, envmap: np.ndarray, balls, material: str, mirror_reflectance: float,
           plane_albedo: float | None, upsample: int):
    from objcam.envmap import mitsuba_envmap_to_world, to_mitsuba_bitmap
    from objcam.render import mitsuba_box_bitmap

    if material == "mirror":
        bsdf = {"type": "conductor", "material": "none", "specular_reflectance": {"type": "rgb",
                                                                                  "value": [mirror_reflectance] * 3}}
    else:
        bsdf = {"type": "conductor", "material": material}
    d = {"type": "scene",
         "emitter": {"type": "envmap",
                     "bitmap": mi.Bitmap(to_mitsuba_bitmap(mitsuba_box_bitmap(envmap, upsample))),
                     "to_world": mi.ScalarTransform4f(mitsuba_envmap_to_world().tolist())}}
    for i, (centre, radius) in enumerate(balls):
        d[f"ball{i}"] = {"type": "sphere", "center": [float(x) for x in centre], "radius": float(radius),
                         "bsdf": dict(bsdf)}
    if plane_albedo is not None:
        d["plane"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([20.0, 20.0, 1.0]),
                      "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [plane_albedo] * 3}}}
    return mi.load_dict(d)


def _material_reflectance(mi, material: str, mirror_reflectance: float) -> Reflectance:
    if material == "mirror":
        return Reflectance(reflectance=mirror_reflectance, fresnel="none")
    p = mi.traverse(mi.load_dict({"type": "conductor", "material": material}))
    eta = tuple(float(x) for x in np.ravel(p["eta.value"]))
    k = tuple(float(x) for x in np.ravel(p["k.value"]))
    return Reflectance(reflectance=None, fresnel="conductor", eta=eta, k=k)


def render_probe(envmap: str | np.ndarray = "forest", *, radius: float = 0.025, centre=None,
                 distance: float = 0.35, elevation_deg: float = 25.0, azimuth_deg: float = 0.0,
                 size: int | tuple[int, int] = 256, ball_px: float = 150.0, offset_px=(0.0, 0.0),
                 material: str = "Cr", mirror_reflectance: float = 0.65, plane_albedo: float | None = None,
                 spp: int = 64, seed: int = 0, upsample: int = 16, camera: Camera | None = None,
                 extra_balls: Sequence[tuple[Sequence[float], float]] = (),
                 band_px: float | None = None) -> ProbeRender:
    """Render a chrome ball (default 5 cm diameter, centre at (0, 0, radius)) under ``envmap`` (bundled name or
    array in objcam's convention) with :func:`objcam.render.render_image` (``spp`` independent samples per pixel,
    box pixel filter). ``camera`` overrides the one :func:`probe_camera` builds. ``extra_balls``: more
    (centre, radius) balls of the same material (for bad-input tests). ``band_px``: render only the pixels within
    that many pixels of the ball's silhouette, the rest 0 (rim-fit tests on large balls at a fraction of the
    cost). Returns the clean HDR render and truth.

    Monte Carlo noise: a mirror needs no light sampling (every sample is exact), the only noise is which part
    of each pixel's footprint a sample hits; a sun spanning ~1 pixel thus gets +-5-10 % energy noise at 64
    spp (binomial coverage), which dominates any per-texel error metric on a sunny map at small sizes."""
    import time

    from objcam.render import render_image
    from objcam.scene import use_mitsuba
    from objcam.synth.assets import load_bundled_envmap

    env = load_bundled_envmap(envmap) if isinstance(envmap, str) else np.asarray(envmap, np.float32)
    c = np.array([0.0, 0.0, radius]) if centre is None else np.asarray(centre, np.float64)
    cam = camera or probe_camera(c, radius, distance, elevation_deg, azimuth_deg, size, ball_px, offset_px)
    mi = use_mitsuba()
    scene = _scene(mi, env, [(c, radius), *extra_balls], material, mirror_reflectance, plane_albedo, upsample)
    t0 = time.perf_counter()
    depth = 3 if plane_albedo is not None else 2
    if band_px is None:
        clean = render_image(scene, cam, spp=spp, max_depth=depth, seed=seed)
    else:
        clean = _render_band(scene, cam, c, float(radius), band_px, spp, depth, seed)
    secs = time.perf_counter() - t0
    return ProbeRender(clean, cam, c, float(radius), env, _material_reflectance(mi, material, mirror_reflectance),
                       spp, secs)


def _render_band(scene, cam: Camera, centre: np.ndarray, radius: float, band_px: float, spp: int, depth: int,
                 seed: int) -> np.ndarray:
    """(H, W, 3) float32: the pixels within ``band_px`` of the silhouette rendered (box filter), the rest 0."""
    import cv2

    from objcam.probe.silhouette import silhouette_px
    from objcam.render import render_rays

    poly = silhouette_px(cam, centre[None], radius, 2048)[0]
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.polylines(mask, [np.round(poly * 4).astype(np.int32)], True, 1,
                  thickness=2 * int(np.ceil(band_px)) + 1, shift=2)
    vv, uu = np.nonzero(mask)
    out = np.zeros((cam.height, cam.width, 3), np.float32)
    out[vv, uu] = render_rays(scene, uu.astype(np.float32), vv.astype(np.float32), cam, spp, depth, seed)
    return out


def make_bracket(clean: np.ndarray, times: Sequence[float] | None = None, *, n_frames: int | None = None,
                 stop_step: float = 2.0, full_well: float = 20000.0, read_noise: float = 3.0,
                 noise: bool = True, seed: int = 0, name: str = "probe") -> ProbeBracket:
    """An exposure bracket of ``clean`` (scene radiance) and its merge.

    Frame k records ``clean * times[k]`` (the gain is folded into the times: 1 radiance unit for 1 s reaches the
    white level) with Poisson shot noise for ``full_well`` electrons at the white level and Gaussian read noise,
    clipped at 1.0 (white level) and flagged saturated there. ``times`` default: the longest frame puts the
    ball's median pixel at 0.25 of the white level; then ``stop_step`` EV shorter each, until the brightest pixel
    sits below 0.5 (``n_frames`` overrides the count). The merge's ``reference`` units equal scene radiance times
    the longest time; :attr:`ProbeBracket.hdr` divides that back out.
    """
    from objcam.capture.hdr import merge_frames
    from objcam.capture.raw import LinearImage
    from objcam.synth.noise import apply_noise

    clean = np.asarray(clean, np.float64)
    if times is None:
        lum = clean.max(axis=2)
        pos = lum[lum > 0]
        t_long = 0.25 / max(float(np.median(pos)) if pos.size else 1.0, 1e-30)
        if n_frames is None:
            n_frames = 1
            while t_long * 2.0 ** (-stop_step * (n_frames - 1)) * float(lum.max()) > 0.5 and n_frames < 16:
                n_frames += 1
        times = [t_long * 2.0 ** (-stop_step * k) for k in range(n_frames)]
    rng = np.random.default_rng(seed)
    frames = []
    for k, t in enumerate(times):
        img, clipped = apply_noise(clean * t, full_well, read_noise, 1.0, rng, noise=noise)
        frames.append(LinearImage(rgb=img, saturated=clipped, path=Path(f"{name}_{k}_{t:.3g}s.exr"),
                                  sensor_shape=img.shape[:2]))
    merge = merge_frames(frames, list(times))
    scale = float(merge.reference_time)
    return ProbeBracket(frames, list(times), merge, merge.radiance / np.float32(scale), scale)


def write_ingest_probe(folder: Path, bracket: ProbeBracket, frame_folder: str = "probe") -> None:
    """Write a merged bracket in the ingest stage's contract (``ingest/probes/<name>/``): ``image.exr`` (linear
    RGB float32, exposure-normalised: scene radiance x 1 s, as :attr:`ProbeBracket.hdr`), ``valid.png`` (255 =
    usable, 0 = saturated in every frame) and ``merge.json`` (as objcam.capture.photos writes it: frame file
    names, their capture-relative ``folder``, ``exposure_times_s`` ascending, saturated fraction, ``n_fallback``:
    pixels with no usable frame). For tests and benchmarks of the probe stage."""
    import json

    from objcam.image_io import atomic_write_text, write_exr, write_png

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_exr(folder / "image.exr", bracket.hdr)
    valid = np.asarray(bracket.merge.valid, bool)
    write_png(folder / "valid.png", valid.astype(np.float64))
    info = {"frames": [Path(p).name for p in bracket.merge.paths], "folder": frame_folder,
            "exposure_times_s": [float(t) for t in bracket.merge.times], "units": "per_second",
            "saturated_fraction": float(1.0 - valid.mean()), "n_invalid": int((~valid).sum()),
            "n_fallback": int(bracket.merge.n_fallback), "frames_used_mean": float(bracket.merge.frames_used.mean())}
    atomic_write_text(folder / "merge.json", json.dumps(info, indent=2))
