"""The probe stage's artifact folder (``objcam/probe/``, data_layout.md ``### probe/<name>/``): file names, the
writer for one probe, and the readers :mod:`objcam.probe.truth` uses.

Every lat-long file here (EXR and PNG) is in the standard file convention (objcam.envmap.to_file). Per probe
``<name>/``:
    envmap_gt.exr          (Hf, 2Hf, 3) float32 fine lat-long radiance (world frame), 0 where not
                           observed (blind spot, camera reflection, outside the image)
    flags.png              (Hf, 2Hf) uint8 mask bits of objcam.probe.unwrap (0 valid, 1 blind, 2 camera,
                           4 saturated, 8 outside): lets a reader area-average to any other resolution
    valid.png              (Hf, 2Hf) 255 = valid texel (flags == 0)
    envmap_gt_<H>.exr      (H, 2H, 3) area-averaged to the solve resolution H (observed fine texels, solid-angle
                           weighted)
    valid_<H>.png          255 where >= min_valid_fraction of the texel's solid angle is valid and none of it is
                           saturated
    saturated_<H>.png      255 where some fine texel is saturated (value there is a lower bound)
    envmap_gt.png, envmap_gt_<H>.png   tonemapped (one exposure: the fine map's 99th percentile over valid texels,
                           gamma 2.2; invalid texels dimmed to 1/4)
    ball.png               the probe photo around the ball (tonemapped) with the fitted silhouette in green
    probe.json             fit, reflectance, masks, saturation (lower-bound energies), warnings
and ``probes.json`` at the top: ``{"format": 1, "env_height": H, "probes": {name: {illumination, folder,
valid_fraction_solid_angle, lower_bound}}}``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from objcam.envmap import from_file, read_latlong, write_latlong, write_latlong_png
from objcam.image_io import atomic_write_text, tonemap, write_png

INDEX = "probes.json"
FORMAT = 1


def coarse_names(height: int) -> tuple[str, str, str]:
    """(envmap, valid, saturated) file names at ``height`` rows."""
    return f"envmap_gt_{height}.exr", f"valid_{height}.png", f"saturated_{height}.png"


def write_mask(path: Path, mask: np.ndarray) -> None:
    """A lat-long mask (objcam's grid) as a PNG in the standard file convention."""
    write_latlong_png(path, np.asarray(mask, bool).astype(np.float64))


def write_uint8(path: Path, a: np.ndarray) -> None:
    """A lat-long uint8 map (objcam's grid) as a PNG in the standard file convention."""
    write_latlong_png(path, np.asarray(a, np.float64) / 255.0)


def read_uint8(path: Path) -> np.ndarray:
    """A lat-long uint8 PNG (standard file convention) as objcam's grid."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(path)
    return from_file(img if img.ndim == 2 else img[..., 0])


def _dimmed(env: np.ndarray, valid: np.ndarray, ref: float) -> np.ndarray:
    disp, _ = tonemap(env, ref)
    return disp * np.where(valid[..., None], 1.0, 0.25)


def write_probe(folder: Path, fine_env: np.ndarray, flags: np.ndarray, coarse_env: np.ndarray,
                coarse_valid: np.ndarray, coarse_sat: np.ndarray, record: dict) -> None:
    """Write one probe's files (see the module doc) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    valid = flags == 0
    h = coarse_env.shape[0]
    write_latlong(folder / "envmap_gt.exr", fine_env)
    write_uint8(folder / "flags.png", flags)
    write_mask(folder / "valid.png", valid)
    e_name, v_name, s_name = coarse_names(h)
    write_latlong(folder / e_name, coarse_env)
    write_mask(folder / v_name, coarse_valid)
    write_mask(folder / s_name, coarse_sat)
    vals = fine_env[valid]
    ref = float(np.percentile(vals, 99)) if vals.size else None
    _, ref = tonemap(fine_env, ref)
    write_latlong_png(folder / "envmap_gt.png", _dimmed(fine_env, valid, ref))
    write_latlong_png(folder / f"envmap_gt_{h}.png", _dimmed(coarse_env, coarse_valid, ref))
    record = dict(record, tonemap_reference=ref)
    atomic_write_text(folder / "probe.json", json.dumps(record, indent=2))


def write_ball_png(path: Path, image: np.ndarray, silhouette: np.ndarray, centre_px: np.ndarray,
                   radius_px: float, max_size: int = 512) -> None:
    """The photo cropped to the ball (1.3 radii around it), tonemapped, resized to <= ``max_size``, with the fitted
    silhouette ``silhouette`` (K, 2) image points drawn."""
    import cv2

    h, w = image.shape[:2]
    half = 1.3 * radius_px
    x0, x1 = int(max(np.floor(centre_px[0] - half), 0)), int(min(np.ceil(centre_px[0] + half), w))
    y0, y1 = int(max(np.floor(centre_px[1] - half), 0)), int(min(np.ceil(centre_px[1] + half), h))
    crop = image[y0:y1, x0:x1, :3]
    disp, _ = tonemap(crop)
    s = min(1.0, max_size / max(crop.shape[:2]))
    size = (max(int(round(crop.shape[1] * s)), 1), max(int(round(crop.shape[0] * s)), 1))
    small = cv2.resize(np.ascontiguousarray(disp, np.float32), size, interpolation=cv2.INTER_AREA)
    pts = ((silhouette - [x0, y0] + 0.5) * s - 0.5)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    canvas = np.ascontiguousarray(small[..., ::-1] * 255.0).astype(np.uint8)  # BGR for drawing
    cv2.polylines(canvas, [np.round(pts * 4).astype(np.int32)], True, (0, 255, 0), 1, cv2.LINE_AA, shift=2)
    write_png(path, canvas[..., ::-1].astype(np.float64) / 255.0)


def write_index(out: Path, env_height: int, entries: dict[str, dict]) -> None:
    atomic_write_text(out / INDEX, json.dumps({"format": FORMAT, "env_height": env_height, "probes": entries},
                                              indent=2))


def read_index(stage_dir: Path) -> dict[str, dict]:
    """{name: entry} from ``probes.json``, or from each ``<name>/probe.json`` when the index is missing."""
    stage_dir = Path(stage_dir)
    idx = stage_dir / INDEX
    if idx.is_file():
        return json.loads(idx.read_text()).get("probes", {})
    out = {}
    for p in sorted(stage_dir.glob("*/probe.json")):
        rec = json.loads(p.read_text())
        out[p.parent.name] = {"illumination": rec.get("illumination", p.parent.name), "folder": p.parent.name,
                              "valid_fraction_solid_angle": rec.get("fine", {}).get("valid_fraction_solid_angle", 0.0)}
    return out


def read_fine(folder: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """(envmap (Hf, 2Hf, 3) float32, flags (Hf, 2Hf) uint8, probe.json record) of one probe folder."""
    env = read_latlong(folder / "envmap_gt.exr")[..., :3]
    flags = read_uint8(folder / "flags.png")
    return env, flags, json.loads((folder / "probe.json").read_text())
