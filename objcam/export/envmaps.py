"""Envmap files for other tools. Every map here is in the standard lat-long convention of files (data_layout.md:
+x at the centre column, azimuth clockwise seen from above), which Blender and Mitsuba (with
:data:`MITSUBA_TO_WORLD`) read as they are."""

from __future__ import annotations

from pathlib import Path

import numpy as np

# Mitsuba 3's envmap emitter holding a standard file: local x -> world +y, y -> +z, z -> +x (data_layout.md)
MITSUBA_TO_WORLD = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
MITSUBA_UPSAMPLE = 4  # box texels up to ramps of 1/4 texel (objcam.render.mitsuba_box_bitmap)


def upsample_box(env: np.ndarray, factor: int) -> np.ndarray:
    """(H f, 2H f, C): every texel repeated f x f times (the same box texels, more pixels for a viewer)."""
    if factor < 1:
        raise ValueError("upsample factor must be >= 1")
    return np.repeat(np.repeat(env, factor, axis=0), factor, axis=1) if factor > 1 else env


def mitsuba_bitmap(env_file: np.ndarray) -> np.ndarray:
    """The bitmap (4H + 1, 8H, 3) for Mitsuba's ``envmap`` emitter with :data:`MITSUBA_TO_WORLD` that emits the box
    texels of ``env_file`` (a standard lat-long map): Mitsuba samples its rows at theta = pi i / (rows - 1) and
    interpolates bilinearly, which would blur and shift a plain H-row map (objcam.render.mitsuba_box_bitmap)."""
    from objcam.render import mitsuba_box_bitmap

    return mitsuba_box_bitmap(env_file, MITSUBA_UPSAMPLE)


def write_radiance_hdr(path: Path, image: np.ndarray) -> None:
    """Radiance RGBE .hdr (linear RGB, float32 in), atomically; negative values clipped (RGBE cannot hold them)."""
    import cv2

    from objcam.image_io import atomic_write_bytes

    img = np.ascontiguousarray(np.clip(image[..., :3], 0, None)[..., ::-1], dtype=np.float32)  # RGB -> BGR
    ok, buf = cv2.imencode(".hdr", img)
    if not ok:
        raise OSError(f"cannot encode {path}")
    atomic_write_bytes(path, buf.tobytes())


def write_envmap(folder: Path, name: str, env_file: np.ndarray, upsample: int = 1) -> list[Path]:
    """``name.exr`` and ``name.hdr`` (upsampled by ``upsample`` for display), and ``name_mitsuba.exr`` (the box
    bitmap the Mitsuba scenes load). ``env_file``: (H, 2H, 3) in the standard convention."""
    from objcam.image_io import write_exr

    big = upsample_box(env_file, upsample)
    paths = [folder / f"{name}.exr", folder / f"{name}.hdr", folder / f"{name}_mitsuba.exr"]
    write_exr(paths[0], big)
    write_radiance_hdr(paths[1], big)
    write_exr(paths[2], mitsuba_bitmap(env_file))
    return paths
