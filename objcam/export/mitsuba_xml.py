"""A Mitsuba 3 scene per target: the object and support (OBJ, face normals, diffuse with the albedo), the target's
camera and the recovered envmap, whose render reproduces the solve's prediction image A x.

- Envmap: ``<target>_mitsuba.exr``, the box bitmap of the standard-convention envmap (objcam.export.envmaps),
  with ``to_world`` = local x -> world +y, y -> +z, z -> +x (data_layout.md); id ``envmap`` (its data is
  ``envmap.data`` in ``mi.traverse``).
- Camera: ``perspective`` with ``to_world`` = world_from_camera @ diag(-1, -1, 1, 1) (OpenCV's x right, y down
  -> Mitsuba's x left, y up), the horizontal field of view from fx, and the principal point as Mitsuba's offset
  (a fraction of the film from its centre, opposite in sign to the pixel shift; OpenCV's centre (W - 1) / 2 is
  Mitsuba's W / 2). Mitsuba
  has one focal length: with fx != fy the render is off by their ratio vertically (export.json warns).
- Integrator: ``path`` with ``max_depth`` 2 (direct light) when the transport was direct, else the transport's
  own depth; ``spp`` and ``max_depth`` are ``<default>`` parameters (``mitsuba -D spp=1024 scene.xml``).
- Film: ``hdrfilm`` of the camera's size with a box filter, as objcam's pixels. The solve's prediction is at the
  transport's pooled size: average f x f blocks of the render to compare (``downsample`` in export.json).
"""

from __future__ import annotations

import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from objcam.camera import Camera
from objcam.export.envmaps import MITSUBA_TO_WORLD
from objcam.image_io import atomic_write_text

MITSUBA_FROM_OPENCV = np.diag([-1.0, -1.0, 1.0, 1.0])


def _matrix(m: np.ndarray) -> str:
    return " ".join(repr(float(x)) for x in np.asarray(m, np.float64).ravel())


def sensor_xml(cam: Camera, sensor_id: str, indent: str = "    ") -> str:
    """A ``perspective`` sensor reproducing ``cam`` (module docstring)."""
    to_world = np.asarray(cam.world_from_camera, np.float64) @ MITSUBA_FROM_OPENCV
    fov = math.degrees(2.0 * math.atan(cam.width / (2.0 * cam.fx)))
    # Mitsuba's offset moves the image the other way from OpenCV's principal point (measured: a disk images
    # where Camera.project puts it only with these signs; tests/test_export.py)
    off_x = -(cam.cx + 0.5 - cam.width / 2.0) / cam.width
    off_y = -(cam.cy + 0.5 - cam.height / 2.0) / cam.height
    i = indent
    return "\n".join([
        f'{i}<sensor type="perspective" id={quoteattr(sensor_id)}>',
        f'{i}    <string name="fov_axis" value="x"/>',
        f'{i}    <float name="fov" value="{fov!r}"/>',
        f'{i}    <float name="principal_point_offset_x" value="{off_x!r}"/>',
        f'{i}    <float name="principal_point_offset_y" value="{off_y!r}"/>',
        f'{i}    <float name="near_clip" value="0.001"/>',
        f'{i}    <float name="far_clip" value="1000"/>',
        f'{i}    <transform name="to_world"><matrix value="{_matrix(to_world)}"/></transform>',
        f'{i}    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>',
        f'{i}    <film type="hdrfilm">',
        f'{i}        <integer name="width" value="{cam.width}"/>',
        f'{i}        <integer name="height" value="{cam.height}"/>',
        f'{i}        <string name="pixel_format" value="rgb"/>',
        f'{i}        <rfilter type="box"/>',
        f'{i}    </film>',
        f'{i}</sensor>'])


def _bsdf_xml(rgb: tuple[float, float, float] | None, texture: str | None, nearest: bool = False) -> str:
    if texture is not None:
        filt = '<string name="filter_type" value="nearest"/>' if nearest else ""
        refl = (f'<texture type="bitmap" name="reflectance"><string name="filename" value={quoteattr(texture)}/>'
                f'<boolean name="raw" value="true"/><string name="wrap_mode" value="clamp"/>{filt}</texture>')
    else:
        r, g, b = rgb if rgb is not None else (0.5, 0.5, 0.5)
        refl = f'<rgb name="reflectance" value="{r!r}, {g!r}, {b!r}"/>'
    return f'<bsdf type="diffuse">{refl}</bsdf>'


def write_scene_xml(path: Path, cam: Camera, target: str, envmap_file: str,
                    shapes: list[tuple[str, str, tuple[float, float, float] | None, str | None, bool]],
                    max_depth: int, spp: int = 256) -> Path:
    """Write the scene (module docstring). ``shapes``: (name, OBJ path, rgb or None, albedo EXR path or None,
    whether the texture is looked up without interpolation), paths relative to ``path``'s folder (Mitsuba resolves
    them there)."""
    lines = ['<?xml version="1.0" encoding="utf-8"?>',
             f"<!-- objcam export: target {target}; world metres, z up; render with: mitsuba {path.name} -->",
             '<scene version="3.0.0">',
             f'    <default name="spp" value="{int(spp)}"/>',
             f'    <default name="max_depth" value="{int(max_depth)}"/>',
             '    <integrator type="path"><integer name="max_depth" value="$max_depth"/></integrator>',
             sensor_xml(cam, target),
             '    <emitter type="envmap" id="envmap">',
             f'        <string name="filename" value={quoteattr(envmap_file)}/>',
             f'        <transform name="to_world"><matrix value="{_matrix(MITSUBA_TO_WORLD)}"/></transform>',
             '    </emitter>']
    for name, obj, rgb, tex, nearest in shapes:
        lines += [f'    <shape type="obj" id={quoteattr(name)}>',
                  f'        <string name="filename" value={quoteattr(obj)}/>',
                  '        <boolean name="face_normals" value="true"/>',
                  f"        {_bsdf_xml(rgb, tex, nearest)}",
                  '    </shape>']
    lines.append("</scene>")
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
