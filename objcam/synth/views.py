"""The photogrammetry ring of a synthetic full capture: the object standing on the printed ChArUco board
(objcam.sfm.board) under an environment map, photographed from N views on one or more rings around it.

:func:`render_views` writes ``<out_dir>/<name>.png`` (tonemapped display images, 8 or 16 bit, one shared exposure,
as a camera with fixed settings would take them) and each view's true camera as ``<camera_dir>/<name>.json``
(objcam Camera JSON, OpenCV convention). The scene is the one :func:`objcam.synth.capture.synthesize` renders when given
the board texture as its support albedo (``objcam.sfm.board.write_board_texture`` and its extent), so target
images and views agree.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
from pathlib import Path
from typing import Annotated, Iterator, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from objcam.camera import Camera, look_at
from objcam.errors import InputError
from objcam.sfm.board import BoardSpec



def _check_elevations(v: list[float]) -> list[float]:
    if any(not (0 < e < 90) for e in v):
        raise ValueError("elevations must lie in (0, 90) degrees")
    return v


#: ring elevations in degrees, each in (0, 90) (shared by the ring's and the full capture's params)
RingElevations = Annotated[list[float], AfterValidator(_check_elevations)]

class ViewRingParams(BaseModel):
    """The ring of views. Defaults: the bunny (8 cm) on the default A3 board under ``forest``, 24 views at 800 x 600
    on two rings (30 and 50 degrees elevation, interleaved in azimuth) 0.6 m from the object, 32 spp."""

    model_config = ConfigDict(extra="forbid")
    object: str = Field("bunny", description="'bunny', 'sphere' or a mesh file (scaled to object_height)")
    object_height: float = Field(0.08, gt=0, le=5, description="object height, metres")
    object_albedo: float | tuple[float, float, float] = Field(0.6, description="object albedo, scalar or RGB")
    envmap: str = Field("forest", description="bundled envmap name or an EXR path (standard lat-long file, data_layout.md)")
    envmap_height: int = Field(128, ge=4, le=2048, description="envmap rows used for rendering")
    rotation_deg: float = Field(0.0, description="envmap rotation about +z (objcam.envmap.rotate_z)")
    envmap_upsample: int = Field(2, ge=1, le=16, description="objcam.render.mitsuba_box_bitmap factor")
    board: BoardSpec = Field(default_factory=BoardSpec, description="the printed board under the object")
    texture_px_per_m: float = Field(4000.0, gt=100, description="board texture resolution, texels per metre")
    plane_size: float = Field(20.0, gt=0, description="side of the support plane, metres (paper beyond the board)")
    n_views: int = Field(24, ge=1, le=512, description="number of views, spread over the rings")
    elevations_deg: RingElevations = Field([30.0, 50.0], min_length=1, description="ring elevations, degrees")
    azimuth0_deg: float = Field(0.0, description="azimuth of the first view, degrees from +x towards +y")
    distance: float = Field(0.6, gt=0, description="camera distance from the look-at point, metres")
    look_at: tuple[float, float, float] | None = Field(
        None, description="point looked at (default: the object's axis at a quarter of its height)")
    width: int = Field(800, ge=16, le=8192)
    height: int = Field(600, ge=16, le=8192)
    fov_deg: float = Field(50.0, gt=1, lt=170, description="horizontal field of view, degrees (fx = fy)")
    spp: int = Field(32, ge=1, description="samples per pixel")
    max_depth: int = Field(4, ge=-1, description="path length (Mitsuba's path integrator)")
    shot_noise: float = Field(0.01, ge=0, description="relative shot noise at the median pixel (0: none)")
    exposure_percentile: float = Field(99.0, gt=0, le=100, description="percentile of the first view mapped to "
                                       "white (the same exposure for every view)")
    bit_depth: Literal[8, 16] = Field(8, description="PNG bit depth")
    seed: int = Field(0, ge=0)



def view_names(params: ViewRingParams) -> list[str]:
    return [f"view_{i:03d}" for i in range(params.n_views)]


def ring_cameras(params: ViewRingParams) -> list[Camera]:
    """The true cameras of the views: the rings share the views as evenly as possible (earlier rings take the
    remainder), each ring evenly spaced in azimuth and offset by a fraction of a step from the previous ring."""
    n_rings = len(params.elevations_deg)
    counts = [params.n_views // n_rings + (1 if k < params.n_views % n_rings else 0) for k in range(n_rings)]
    tgt = np.array(params.look_at if params.look_at is not None else (0.0, 0.0, 0.25 * params.object_height))
    fx = (params.width / 2) / math.tan(math.radians(params.fov_deg) / 2)
    cams = []
    for k, (el_deg, n) in enumerate(zip(params.elevations_deg, counts)):
        for i in range(n):
            az = math.radians(params.azimuth0_deg + 360.0 * (i + k / n_rings) / max(n, 1))
            el = math.radians(el_deg)
            eye = tgt + params.distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                    math.sin(el)])
            cams.append(Camera(width=params.width, height=params.height, fx=fx, fy=fx, cx=(params.width - 1) / 2,
                               cy=(params.height - 1) / 2, world_from_camera=look_at(eye, tgt).tolist()))
    return cams


def _seed(seed: int, index: int) -> int:
    return (seed * 1_000_003 + index * 104_729 + 31) % (2**31)


@contextlib.contextmanager
def board_scene(verts: np.ndarray, faces: np.ndarray, object_albedo, board: BoardSpec, env: np.ndarray,
                texture_px_per_m: float = 4000.0, plane_size: float = 20.0, envmap_upsample: int = 2,
                extra: dict | None = None) -> Iterator:
    """The Mitsuba scene of a full capture: the object (``verts`` (V, 3) world metres, ``faces`` (F, 3)) with a
    constant albedo (scalar or RGB) standing on the printed ``board`` (``board_texture`` on
    ``make_plane(plane_size, extent)``: paper beyond the board) under ``env`` ((H, 2H, 3) objcam lat-long radiance,
    emitted as box texels, ``mitsuba_box_bitmap(env, envmap_upsample)``). ``extra``: more scene-dict entries (an
    ``"object"`` entry replaces the object, e.g. by a chrome ball). A context manager: the scene's files live in a
    temporary folder while it is in use."""
    from objcam.render import mitsuba_box_bitmap
    from objcam.scene import AlbedoValue, MeshData, SceneDescription, build_mitsuba_scene, make_plane
    from objcam.sfm.board import board_texture
    from objcam.image_io import write_exr

    tex = board_texture(board, texture_px_per_m)
    if tex.extent > plane_size:
        raise InputError("the board is larger than the support plane", None, "raise plane_size")
    rgb = (object_albedo,) * 3 if isinstance(object_albedo, (int, float)) else tuple(object_albedo)
    with tempfile.TemporaryDirectory(prefix="objcam-board-scene-") as tmp:
        root = Path(tmp)
        MeshData(np.asarray(verts, np.float32), np.asarray(faces, np.uint32)).save(root / "object.npz")
        make_plane(plane_size, tex.extent).save(root / "support.npz")
        write_exr(root / "albedo_support.exr", np.repeat(tex.image[..., None], 3, axis=2))
        desc = SceneDescription(object_mesh="object.npz", support_mesh="support.npz", support_is_plane=True,
                                albedo_object=AlbedoValue(rgb=tuple(float(x) for x in rgb)),
                                albedo_support=AlbedoValue(texture="albedo_support.exr"))
        yield build_mitsuba_scene(desc, root, envmap=mitsuba_box_bitmap(np.asarray(env, np.float32),
                                                                        envmap_upsample), extra=extra)


def render_views(out_dir: str | Path, params: ViewRingParams | None = None,
                 camera_dir: str | Path | None = None) -> list[tuple[Path, Camera]]:
    """Render the ring of views into ``out_dir`` (``view_000.png`` ...) and write each true camera as
    ``<camera_dir>/view_000.json`` (default ``camera_dir`` = ``out_dir``). Returns [(image path, true camera)].

    Each view: path-traced linear radiance (objcam.render.render_image), shot noise (objcam.synth.noise.apply_noise,
    ``shot_noise`` relative at the median pixel), then one exposure for all views (the first view's
    ``exposure_percentile`` maps to white), gamma 2.2, quantised to ``bit_depth`` bits.
    """
    import cv2

    from objcam.envmap import rotate_z
    from objcam.image_io import atomic_write_bytes
    from objcam.progress import bar
    from objcam.render import render_image
    from objcam.synth.assets import load_envmap, object_mesh
    from objcam.synth.noise import apply_noise, auto_exposure

    params = params or ViewRingParams()
    out = Path(out_dir)
    cam_dir = Path(camera_dir) if camera_dir is not None else out
    out.mkdir(parents=True, exist_ok=True)
    cam_dir.mkdir(parents=True, exist_ok=True)
    names = view_names(params)
    cams = ring_cameras(params)
    verts, faces = object_mesh(params.object, params.object_height)
    env = load_envmap(params.envmap, params.envmap_height).astype(np.float64)
    env = rotate_z(env, params.rotation_deg).astype(np.float32)

    results: list[tuple[Path, Camera]] = []
    ref = None
    with board_scene(verts, faces, params.object_albedo, params.board, env, params.texture_px_per_m,
                     params.plane_size, params.envmap_upsample) as scene:
        for i, (name, cam) in enumerate(zip(names, bar(cams, desc="views", unit="view"))):
            img = render_image(scene, cam, params.spp, params.max_depth, seed=_seed(params.seed, i))
            if params.shot_noise > 0:
                rng = np.random.default_rng([params.seed, 7, i])
                img, _ = apply_noise(img, auto_exposure(img, params.shot_noise), 0.0, None, rng)
            if ref is None:
                pos = img[img > 0]
                ref = float(np.percentile(pos, params.exposure_percentile)) if pos.size else 1.0
            disp = np.clip(np.maximum(img, 0) / ref, 0.0, 1.0) ** (1 / 2.2)
            scale = 255.0 if params.bit_depth == 8 else 65535.0
            q = (disp * scale + 0.5).astype(np.uint8 if params.bit_depth == 8 else np.uint16)
            ok, buf = cv2.imencode(".png", np.ascontiguousarray(q[..., ::-1]))
            if not ok:
                raise OSError(f"cannot encode {out / name}.png")
            path = out / f"{name}.png"
            atomic_write_bytes(path, buf.tobytes())
            cam.save(cam_dir / f"{name}.json")
            results.append((path, cam))
    return results
