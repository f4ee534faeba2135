"""Synthetic *photographed* captures (``objcam synth OUT --full``): what a photographer with a DSLR brings home.

The object (a 3D print of a known shape) stands on the printed ChArUco board (``objcam.sfm.board``) under an
environment map. Rendered with Mitsuba (``objcam.synth.views.board_scene``) and written as camera raws:

- a ring of views (``objcam.synth.views.ring_cameras``), one raw each, one fixed exposure (manual mode);
- per illumination (envmap rotation) one target: the object and its shadows from a tripod camera, path-traced
  with interreflections, as an exposure bracket;
- per illumination a chrome ball (Mitsuba conductor ``Cr``) resting on the board in place of the object, seen
  from the same tripod camera, as an exposure bracket (``[[probes]]``, named after the target it is truth for).

Raws: Bayer RGGB DNGs (``objcam.capture.dng.write_dng``, PiDNG) with EXIF exposure time, ISO and f-number,
black/white levels, as-shot white balance and the sensor noise model (Poisson shot noise for ``full_well_e``
electrons at the white level, Gaussian read noise, 14-bit quantisation, clipping at the white level). The
sensor has 2 x 2 binned pixels: each rendered pixel covers one 2 x 2 Bayer tile, so LibRaw's raw data decoded
with ``demosaic = "superpixel"`` (the manifest's default) is the render at ``width`` x ``height``, and the true
cameras in ``truth/cameras/`` are at that size. Channel sensitivities are 1 / ``wb`` (the as-shot white balance
undoes them), so ``white_balance = "camera"`` gives raw-linear values proportional to the scene's radiance:
decoded value / exposure time = ``gain`` x radiance (``truth.json`` ``sensor.gain``).

Layout (paths relative to the capture folder)::

    capture.toml                       photographed flavour: [camera], [views], [board], targets with folder,
                                       [[probes]], scene.object = "object.ply"
    object.ply                         the known shape IN ITS OWN FRAME: bounding box centred on the origin,
                                       turned by -``object_yaw_deg`` about z, in millimetres (like a printer's STL)
    views/view_000.dng ...             the ring of views
    targets/<name>/frame_00.dng ...    one bracket per illumination (longest exposure first)
    probes/<name>/frame_00.dng ...     the chrome ball's bracket for that illumination
    truth/truth.json                   what is where (below); never read by the pipeline
    truth/envmap.exr | truth/<name>/envmap.exr   the rotated envmap(s) rendered (standard lat-long file)
    truth/cameras/views/<stem>.json    true cameras at the decoded (superpixel) size
    truth/cameras/targets/<name>.json, truth/cameras/probes/<name>.json
    truth/targets/<name>/clean.exr     noise-free target in ingest's units (decoded value per second)
    truth/probes/<name>/clean.exr      noise-free chrome-ball image, same units
    truth/object_world.ply             the object in world metres (resting on z = 0)
    truth/object_pose.json             world_from_object (4x4, includes the mm -> m scale), yaw, scale
    truth/albedo_support.exr           the board's albedo texture (extent in truth.json)
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from objcam.camera import Camera, look_at
from objcam.errors import InputError
from objcam.sfm.board import BoardSpec
from objcam.synth.views import RingElevations

RGB = tuple[float, float, float]


class FullSynthParams(BaseModel):
    """A synthetic photographed capture. Defaults (about 2-3 minutes on 2 cores): the 8 cm bunny on the A3 board
    under ``forest``, 16 views at 640 x 480 (16 spp), one target (5-frame bracket, 128 spp, interreflections) and
    one chrome ball of 5 cm (7-frame bracket)."""

    model_config = ConfigDict(extra="forbid")
    object: str = Field("bunny", description="'bunny', 'sphere' or a mesh file (scaled to object_height)")
    object_height: float = Field(0.08, gt=0, le=1, description="object height, metres")
    object_albedo: Union[float, RGB] = Field(0.6, description="object albedo, scalar or [r, g, b]")
    object_yaw_deg: float = Field(30.0, description="rotation of object.ply's own frame about z, degrees (the "
                                  "geometry stage must find it)")
    object_units: Literal["mm", "m"] = Field("mm", description="units of object.ply")
    albedo_known: bool = Field(False, description="write the object albedo and the board texture into "
                               "capture.toml [albedo] (default: unknown, as for a real capture)")
    envmap: str = Field("forest", description="bundled envmap name or an EXR path (standard lat-long file, data_layout.md)")
    envmap_height: int = Field(128, ge=4, le=2048, description="envmap rows used for rendering and as truth")
    envmap_upsample: int = Field(2, ge=1, le=16, description="objcam.render.mitsuba_box_bitmap factor")
    rotations_deg: list[float] = Field([0.0], min_length=1, description="envmap rotations about +z: one "
                                       "illumination (target, probe) each; the views use the first")
    board: BoardSpec = Field(default_factory=BoardSpec, description="the printed board (JSON object)")
    texture_px_per_m: float = Field(4000.0, gt=100, description="board texture resolution, texels per metre")
    plane_size: float = Field(20.0, gt=0, description="side of the support plane (paper), metres")
    n_views: int = Field(16, ge=3, le=512, description="views in the ring")
    elevations_deg: RingElevations = Field([30.0, 50.0], min_length=1, description="ring elevations, degrees")
    view_distance: float = Field(0.6, gt=0, description="view camera distance from the object, metres")
    width: int = Field(640, ge=32, le=8192, description="decoded image width (sensor: twice), pixels")
    height: int = Field(480, ge=32, le=8192, description="decoded image height (sensor: twice), pixels")
    fov_deg: float = Field(50.0, gt=1, lt=170, description="horizontal field of view, degrees (one lens for all)")
    view_spp: int = Field(16, ge=1, description="samples per pixel of the views")
    view_max_depth: int = Field(4, ge=-1, description="path length of the views")
    target_azimuth_deg: float = Field(-90.0, description="tripod camera azimuth, degrees from +x towards +y")
    target_elevation_deg: float = Field(40.0, gt=0, lt=90, description="tripod camera elevation, degrees")
    target_distance: float = Field(0.45, gt=0, description="tripod camera distance from the object, metres")
    target_spp: int = Field(128, ge=1, description="samples per pixel of the targets")
    max_depth: int = Field(6, ge=-1, description="path length of the targets (interreflections)")
    bracket_frames: int = Field(5, ge=1, le=16, description="frames per target bracket")
    bracket_stop: float = Field(2.0, gt=0, le=6, description="EV between bracket frames")
    probe: bool = Field(True, description="photograph a chrome ball per illumination ([[probes]])")
    probe_diameter: float = Field(0.05, gt=0, description="chrome ball diameter, metres")
    probe_spp: int = Field(32, ge=1, description="samples per pixel of the chrome-ball frames")
    probe_centre_known: bool = Field(True, description="the ball sits on the board's centre mark and the manifest "
                                     "gives its centre (issue 5's protocol; found by the probe stage otherwise: on "
                                     "a busy board a ball under ~150 px is hard to tell from the print)")
    probe_bracket_frames: int = Field(7, ge=1, le=16, description="frames per chrome-ball bracket")
    iso: float = Field(100.0, gt=0)
    f_number: float = Field(8.0, gt=0)
    view_exposure_s: float = Field(1 / 30, gt=0, description="exposure time of the views, seconds; the sensor "
                                   "gain is set so that the first view's 99th percentile reaches 0.8 of white")
    black_level: int = Field(512, ge=0, le=60000)
    white_level: int = Field(16383, gt=0, le=65535)
    full_well_e: float = Field(20000.0, gt=0, description="electrons at the white level (base ISO)")
    read_noise_e: float = Field(3.0, ge=0, description="read noise, electrons")
    noise: bool = Field(True, description="apply the sensor noise model")
    wb: RGB = Field((2.0, 1.0, 1.5), description="as-shot white balance multipliers (R, G, B)")
    max_size: int | None = Field(None, description="[views] max_size written to capture.toml (default: the "
                                 "larger image side, no downsampling)")
    seed: int = Field(0, ge=0)

    @field_validator("rotations_deg")
    @classmethod
    def _rots(cls, v: list[float]) -> list[float]:
        if len({_rot_name(r) for r in v}) != len(v):
            raise ValueError("rotations_deg has duplicates")
        return v


def _rot_name(deg: float) -> str:
    return f"{deg:g}".replace("+", "")


def target_names(params: FullSynthParams) -> list[tuple[str, float]]:
    """(name, rotation) per illumination: ``t0`` for a single one, else ``rot<deg>``."""
    if len(params.rotations_deg) == 1:
        return [("t0", params.rotations_deg[0])]
    return [(f"rot{_rot_name(r)}", r) for r in params.rotations_deg]


def view_params(params: FullSynthParams):
    """The ring of views as objcam.synth.views.ViewRingParams (for its cameras)."""
    from objcam.synth.views import ViewRingParams

    return ViewRingParams(object=params.object, object_height=params.object_height,
                          object_albedo=params.object_albedo, envmap=params.envmap,
                          envmap_height=params.envmap_height, rotation_deg=params.rotations_deg[0],
                          envmap_upsample=params.envmap_upsample, board=params.board,
                          texture_px_per_m=params.texture_px_per_m, plane_size=params.plane_size,
                          n_views=params.n_views, elevations_deg=params.elevations_deg,
                          distance=params.view_distance, width=params.width, height=params.height,
                          fov_deg=params.fov_deg, spp=params.view_spp, max_depth=params.view_max_depth,
                          seed=params.seed)


def target_camera(params: FullSynthParams) -> Camera:
    """The tripod camera: the views' lens and size, looking at the object's axis at a quarter of its height."""
    tgt = np.array([0.0, 0.0, 0.25 * params.object_height])
    az, el = math.radians(params.target_azimuth_deg), math.radians(params.target_elevation_deg)
    eye = tgt + params.target_distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                   math.sin(el)])
    fx = (params.width / 2) / math.tan(math.radians(params.fov_deg) / 2)
    return Camera(width=params.width, height=params.height, fx=fx, fy=fx, cx=(params.width - 1) / 2,
                  cy=(params.height - 1) / 2, world_from_camera=look_at(eye, tgt).tolist())


def object_pose(params: FullSynthParams, verts_world: np.ndarray) -> np.ndarray:
    """4x4 world_from_object of object.ply: p_world = s R_z(yaw) p_obj + t, with s the unit scale (0.001 for
    millimetres) and t chosen so that object.ply's own bounding box is centred on its origin."""
    s = 0.001 if params.object_units == "mm" else 1.0
    a = math.radians(params.object_yaw_deg)
    R = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    q = np.asarray(verts_world, np.float64) @ R / s  # R^T p / s: the object turned back, in its units
    c_obj = (q.min(axis=0) + q.max(axis=0)) / 2
    m = np.eye(4)
    m[:3, :3] = s * R
    m[:3, 3] = s * R @ c_obj
    return m


def _seed(seed: int, kind: int, index: int) -> int:
    return (seed * 1_000_003 + kind * 65_537 + index * 7919 + 101) % (2**31)


def _bin2(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) -> (2H, 2W, 3): each rendered pixel fills one 2 x 2 Bayer tile (a 2 x 2 binned sensor)."""
    return np.repeat(np.repeat(np.asarray(img, np.float64), 2, axis=0), 2, axis=1)


class _Sensor:
    """Writes renders (radiance) as DNG frames: signal = radiance x gain x t / wb (white-level units)."""

    def __init__(self, params: FullSynthParams, gain: float):
        from objcam.capture.dng import NoiseModel

        self.p, self.gain = params, gain
        self.wb = np.asarray(params.wb, np.float64)
        self.noise = NoiseModel(params.full_well_e, params.read_noise_e, params.iso, params.seed) \
            if params.noise else None
        self.count = 0
        # the zoom setting in EXIF, as an APS-C camera (23.5 mm sensor width) with this field of view
        self.focal_mm = round(11.75 / math.tan(math.radians(params.fov_deg) / 2), 1)

    def write(self, path: Path, radiance: np.ndarray, t: float) -> dict:
        from objcam.capture.dng import NoiseModel, write_dng

        signal = _bin2(radiance) * (self.gain * t) / self.wb
        noise = None
        if self.noise is not None:  # a different noise draw per file
            noise = NoiseModel(self.noise.full_well_e, self.noise.read_noise_e, self.noise.base_iso,
                               _seed(self.p.seed, 9, self.count))
        self.count += 1
        write_dng(path, signal, exposure_time=t, iso=self.p.iso, f_number=self.p.f_number, make="objcam",
                  model="synthetic full", black_level=self.p.black_level, white_level=self.p.white_level,
                  wb=tuple(float(x) for x in self.wb), noise=noise, focal_length_mm=self.focal_mm)
        return {"file": path.name, "exposure_time_s": t, "saturated_fraction": float(np.mean(
            np.max(signal, axis=2) >= 1.0))}


def _nice_time(t: float) -> float:
    """The power-of-two second nearest to ``t`` (camera-like shutter steps, exact in EXIF rationals)."""
    return float(2.0 ** round(math.log2(t)))


def bracket_times(per_second: np.ndarray, n: int, stop: float, median_level: float = 0.25) -> list[float]:
    """Exposure times, longest first: the longest puts the median pixel's brightest channel at about
    ``median_level`` of white (a power-of-two time), then ``stop`` EV shorter each."""
    lum = np.max(per_second, axis=2)
    pos = lum[lum > 0]
    t_long = _nice_time(median_level / max(float(np.median(pos)) if pos.size else 1.0, 1e-30))
    return [t_long * 2.0 ** (-stop * k) for k in range(n)]


def _toml(v) -> str:
    from objcam.synth.capture import _toml_value

    return _toml_value(v)


def synthesize_full(out_dir: str | Path, params: FullSynthParams | None = None) -> dict:
    """Render the synthetic photographed capture ``params`` into ``out_dir`` (created; must be empty if it
    exists). Returns a summary (files, exposure times, seconds)."""
    from objcam.envmap import rotate_z, write_latlong
    from objcam.image_io import atomic_write_text, write_exr
    from objcam.progress import bar
    from objcam.render import render_image
    from objcam.sfm.board import board_texture
    from objcam.synth.assets import load_envmap, object_mesh, write_ply
    from objcam.synth.views import board_scene, ring_cameras, view_names

    params = params or FullSynthParams()
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("output folder exists and is not empty", out, "give a new or empty folder")
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    truth = out / "truth"

    # the object: world mesh for rendering and truth, its own frame for the manifest
    verts, faces = object_mesh(params.object, params.object_height)
    pose = object_pose(params, verts)
    inv = np.linalg.inv(pose)
    verts_obj = (verts.astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32)
    write_ply(out / "object.ply", verts_obj, faces)
    write_ply(truth / "object_world.ply", verts, faces)
    yaw = params.object_yaw_deg
    atomic_write_text(truth / "object_pose.json", json.dumps({
        "world_from_object": pose.tolist(), "yaw_deg": yaw, "unit_scale": 0.001 if params.object_units == "mm"
        else 1.0, "units": params.object_units,
        "note": "p_world = world_from_object @ [p_object, 1]; object.ply's bounding box is centred on its "
                "origin"}, indent=2))
    tex = board_texture(params.board, params.texture_px_per_m)
    write_exr(truth / "albedo_support.exr", np.repeat(tex.image[..., None], 3, axis=2))

    env0 = load_envmap(params.envmap, params.envmap_height).astype(np.float64)
    targets = target_names(params)
    per_target_env = len(targets) > 1
    vcams = ring_cameras(view_params(params))
    vnames = view_names(view_params(params))
    tcam = target_camera(params)
    radius = params.probe_diameter / 2
    ball = {"type": "sphere", "center": [0.0, 0.0, radius], "radius": radius,
            "bsdf": {"type": "conductor", "material": "Cr"}}
    summary: dict = {"out_dir": str(out), "views": {}, "targets": {}, "probes": {}, "render_seconds": {}}
    truth_targets: dict = {}
    truth_probes: dict = {}
    envmaps_rel: dict = {}
    sensor: _Sensor | None = None
    n_renders = len(vcams) + len(targets) * (1 + int(params.probe))
    progress = bar(total=n_renders, desc="synth --full renders", unit="image")

    for ti, (name, rot) in enumerate(targets):
        env = rotate_z(env0, rot).astype(np.float32)
        if per_target_env:
            write_latlong(truth / name / "envmap.exr", env)
            envmaps_rel[name] = f"truth/{name}/envmap.exr"
        else:
            write_latlong(truth / "envmap.exr", env)
            envmaps_rel[name] = "truth/envmap.exr"
        with board_scene(verts, faces, params.object_albedo, params.board, env, params.texture_px_per_m,
                         params.plane_size, params.envmap_upsample) as scene:
            if ti == 0:  # the ring of views, under the first illumination
                t0 = time.perf_counter()
                for i, (vn, cam) in enumerate(zip(vnames, vcams)):
                    img = render_image(scene, cam, params.view_spp, params.view_max_depth,
                                       seed=_seed(params.seed, 1, i))
                    if sensor is None:  # fix the gain on the first view (camera in manual mode)
                        pos = img[img > 0]
                        p99 = float(np.percentile(pos, 99.0)) if pos.size else 1.0
                        sensor = _Sensor(params, 0.8 / (p99 * params.view_exposure_s))
                    summary["views"][vn] = sensor.write(out / "views" / f"{vn}.dng", img, params.view_exposure_s)
                    cam.save(truth / "cameras" / "views" / f"{vn}.json")
                    progress.update(1)
                summary["render_seconds"]["views"] = round(time.perf_counter() - t0, 1)
            assert sensor is not None
            t0 = time.perf_counter()
            clean = render_image(scene, tcam, params.target_spp, params.max_depth, seed=_seed(params.seed, 2, ti))
            summary["render_seconds"][f"target {name}"] = round(time.perf_counter() - t0, 1)
            progress.update(1)
        per_s = clean * sensor.gain  # ingest's units: decoded value per second (camera white balance applied)
        times = bracket_times(per_s / sensor.wb, params.bracket_frames, params.bracket_stop)
        frames = [sensor.write(out / "targets" / name / f"frame_{k:02d}.dng", clean, t) for k, t in enumerate(times)]
        tcam.save(truth / "cameras" / "targets" / f"{name}.json")
        write_exr(truth / "targets" / name / "clean.exr", per_s.astype(np.float32))
        truth_targets[name] = {"rotation_deg": rot, "envmap": envmaps_rel[name],
                               "camera": f"truth/cameras/targets/{name}.json",
                               "clean_image": f"truth/targets/{name}/clean.exr", "frames": frames,
                               "spp": params.target_spp, "max_depth": params.max_depth}
        summary["targets"][name] = {"frames": len(frames), "times": times}

        if params.probe:
            t0 = time.perf_counter()
            with board_scene(verts, faces, params.object_albedo, params.board, env, params.texture_px_per_m,
                             params.plane_size, params.envmap_upsample, extra={"object": ball}) as scene:
                pclean = render_image(scene, tcam, params.probe_spp, 4, seed=_seed(params.seed, 3, ti))
            summary["render_seconds"][f"probe {name}"] = round(time.perf_counter() - t0, 1)
            progress.update(1)
            pper_s = pclean * sensor.gain
            ptimes = bracket_times(pper_s / sensor.wb, params.probe_bracket_frames, params.bracket_stop)
            pframes = [sensor.write(out / "probes" / name / f"frame_{k:02d}.dng", pclean, t)
                       for k, t in enumerate(ptimes)]
            tcam.save(truth / "cameras" / "probes" / f"{name}.json")
            write_exr(truth / "probes" / name / "clean.exr", pper_s.astype(np.float32))
            truth_probes[name] = {"illumination": name, "envmap": envmaps_rel[name],
                                  "camera": f"truth/cameras/probes/{name}.json",
                                  "clean_image": f"truth/probes/{name}/clean.exr",
                                  "centre": [0.0, 0.0, radius], "radius": radius, "diameter": params.probe_diameter,
                                  "material": "Cr (Mitsuba conductor, physical Fresnel)", "frames": pframes,
                                  "spp": params.probe_spp, "placement": "in place of the object, resting on the "
                                  "board at the origin; the object is absent from these frames"}
            summary["probes"][name] = {"frames": len(pframes), "times": ptimes}
    progress.close()

    _write_manifest(out, params, targets, tex.extent)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    rgb = [params.object_albedo] * 3 if isinstance(params.object_albedo, (int, float)) else list(params.object_albedo)
    info = {
        "format": 1, "flavour": "photographed",
        "envmaps": envmaps_rel,
        "targets": truth_targets,
        "probes": truth_probes,
        "views": {"cameras": "truth/cameras/views", "names": vnames, "exposure_time_s": params.view_exposure_s,
                  "rotation_deg": params.rotations_deg[0], "spp": params.view_spp,
                  "max_depth": params.view_max_depth},
        "albedo": {"object": {"rgb": rgb, "known": params.albedo_known},
                   "support": {"texture": "truth/albedo_support.exr", "extent": tex.extent, "pattern": "board",
                               "known": params.albedo_known}},
        "object": {"source": params.object, "height_m": params.object_height, "mesh": "object.ply",
                   "mesh_world": "truth/object_world.ply", "pose": "truth/object_pose.json",
                   "world_from_object": pose.tolist(), "bbox_min": lo.tolist(), "bbox_max": hi.tolist(),
                   "faces": int(len(faces))},
        "envmap": {"source": params.envmap, "height": int(env0.shape[0]), "convention": "standard lat-long (data_layout.md)",
                   "rotation": "objcam.envmap.rotate_z(source, rotation_deg)"},
        "sensor": {"gain": sensor.gain if sensor else None,
                   "units": "decoded value (white-level units, camera white balance applied) per second = "
                            "gain x radiance", "binning": "2x2 (superpixel decode = the render's size)",
                   "cfa": "RGGB", "black_level": params.black_level, "white_level": params.white_level,
                   "wb": list(params.wb), "iso": params.iso, "f_number": params.f_number,
                   "full_well_e": params.full_well_e, "read_noise_e": params.read_noise_e, "noise": params.noise},
        "plane_size": params.plane_size,
        "params": params.model_dump(mode="json"),
    }
    atomic_write_text(truth / "truth.json", json.dumps(info, indent=2))
    summary["total_seconds"] = round(time.perf_counter() - t_start, 1)
    return summary


def _write_manifest(out: Path, params: FullSynthParams, targets: list[tuple[str, float]], extent: float) -> None:
    from objcam.image_io import atomic_write_text, write_exr
    from objcam.sfm.board import board_texture

    lines = ["# objcam synthetic photographed capture (objcam synth --full); truth/ is for evaluation only", "",
             "[scene]", 'object = "object.ply"   # the known shape, in its own frame and units (registered by '
             'the geometry stage)', 'support = "plane"', f"plane_size = {_toml(params.plane_size)}"]
    if params.albedo_known:
        tex = board_texture(params.board, params.texture_px_per_m)
        write_exr(out / "albedo_support.exr", np.repeat(tex.image[..., None], 3, axis=2))
        obj = params.object_albedo if isinstance(params.object_albedo, (int, float)) else list(params.object_albedo)
        lines += ["", "[albedo]", f"object = {_toml(float(obj) if not isinstance(obj, list) else obj)}",
                  f'support = {{ texture = "albedo_support.exr", extent = {_toml(extent)} }}']
    lines += ["", "[camera]", 'white_balance = "camera"', 'demosaic = "superpixel"',
              "", "[views]", 'folder = "views"',
              f"max_size = {max(200, params.max_size or max(params.width, params.height))}",
              "", "[board]"]
    lines += [f"{k} = {_toml(v)}" for k, v in params.board.model_dump().items()]
    for name, _ in targets:
        lines += ["", "[[targets]]", f'name = "{name}"', f'folder = "targets/{name}"']
    if params.probe:
        for name, _ in targets:
            lines += ["", "[[probes]]", f'name = "{name}"', f'folder = "probes/{name}"',
                      f"diameter = {_toml(params.probe_diameter)}"]
            if params.probe_centre_known:
                lines.append(f"centre = {_toml([0.0, 0.0, params.probe_diameter / 2])}")
    atomic_write_text(out / "capture.toml", "\n".join(lines) + "\n")
