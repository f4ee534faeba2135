"""A capture's photos as linear images: list a folder, decode one photo, merge one bracket, resize and undistort.

The ``ingest`` stage orchestrates these; each function does one thing and raises InputError naming the file.

Units: linear camera RGB in white-level units (``objcam.capture.raw``) times the capture's white balance,
divided by the exposure time: **decoded value per second** (``per_second``). Photos of one capture at one ISO and
aperture are then proportional to scene radiance with one factor. JPEG/PNG views have no linear data: they are
linearised with the sRGB curve (an approximation of the camera's tone curve; bracketed JPEG targets get a
recovered Debevec response instead, ``objcam.capture.hdr.merge_ldr_bracket``). A linear EXR is taken as already
linear, exposure time 1 s unless capture.toml gives one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from objcam.capture.exif import ExposureInfo, exposure_time, read_exif
from objcam.capture.raw import LDR_EXTENSIONS, RAW_EXTENSIONS, TIFF_EXTENSIONS, UNREADABLE_FIX
from objcam.errors import InputError

EXR_EXTENSIONS = frozenset({".exr"})
PHOTO_EXTENSIONS = RAW_EXTENSIONS | TIFF_EXTENSIONS | LDR_EXTENSIONS | EXR_EXTENSIONS


def kind(path: Path) -> str:
    """"raw", "tiff", "ldr" (JPEG/PNG) or "exr"."""
    ext = Path(path).suffix.lower()
    if ext in RAW_EXTENSIONS:
        return "raw"
    if ext in TIFF_EXTENSIONS:
        return "tiff"
    if ext in LDR_EXTENSIONS:
        return "ldr"
    if ext in EXR_EXTENSIONS:
        return "exr"
    raise InputError(f"not a photo objcam reads ({ext or 'no extension'})", path, UNREADABLE_FIX)


def list_photos(folder: Path, what: str) -> list[Path]:
    """The photos in ``folder`` (sorted by name; hidden files and other files ignored). ``what`` names the folder's
    role in messages ("views", "target t0"). InputError when the folder is missing or holds no photo."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{what}: folder not found", folder, "create it with the photos, or fix the folder in "
                         "capture.toml")
    photos = sorted(p for p in folder.iterdir()
                    if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in PHOTO_EXTENSIONS)
    if not photos:
        raise InputError(f"{what}: no photos in the folder (raw, TIFF, JPEG/PNG or EXR)", folder,
                         "copy the photos there, or fix the folder in capture.toml")
    return photos


@dataclass
class Photo:
    """One decoded photo. ``rgb`` per second (module doc), ``saturated`` where any contributing sample was at or
    near the white level (always False for EXR)."""

    rgb: np.ndarray  # float32 (H, W, 3)
    saturated: np.ndarray  # bool (H, W)
    path: Path
    exposure: ExposureInfo
    time_s: float
    reader: str  # "rawpy superpixel", "tiff16", "srgb", "exr"
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    extra: dict = field(default_factory=dict)


def time_override(path: Path, overrides: Mapping[str, float], capture: Path | None = None,
                  default: float | None = None) -> float | None:
    """The exposure time capture.toml gives for ``path``: ``exposure_times`` keyed by file name or capture-relative
    path (overrides EXIF), else ``default`` (``exposure_time``: every photo without an EXIF exposure time, e.g. a
    folder of exported JPEGs; an EXR is linear as it is and never takes it), else None (EXIF)."""
    if path.name in overrides:
        return float(overrides[path.name])
    if capture is not None:
        try:
            rel = path.resolve().relative_to(Path(capture).resolve()).as_posix()
        except ValueError:
            rel = None
        if rel is not None and rel in overrides:
            return float(overrides[rel])
    if default is not None and kind(path) != "exr":
        from objcam.capture.exif import read_exif

        if read_exif(path).exposure_time is None:
            return float(default)
    return None


def resolve_white_balance(setting, photos: Sequence[Path]) -> tuple[tuple[float, float, float], str]:
    """One white balance for the whole capture, so every image stays comparable: ``"camera"`` / ``"daylight"``
    take the first raw photo's as-shot / daylight multipliers (green = 1), ``"none"`` ones, or the given three.
    Without a raw photo, "camera" and "daylight" mean none (TIFF/JPEG exports are already balanced).
    Returns (multipliers, where they came from)."""
    if isinstance(setting, (tuple, list)):
        return tuple(float(x) for x in setting), "capture.toml"
    if setting == "none":
        return (1.0, 1.0, 1.0), "none"
    raws = [p for p in photos if kind(p) == "raw"]
    if not raws:
        return (1.0, 1.0, 1.0), f"{setting}: no raw photo, none applied"
    from objcam.capture.raw import _open_raw

    first = raws[0]
    raw = _open_raw(first)
    with raw:
        v = np.asarray(raw.camera_whitebalance if setting == "camera" else raw.daylight_whitebalance, float)
    r, g, b = v[0], v[1], v[2]
    if not (r > 0 and g > 0 and b > 0):
        raise InputError(f"the file has no {'as-shot' if setting == 'camera' else 'daylight'} white balance",
                         first, 'set [camera] white_balance = "none" or three multipliers in capture.toml')
    return (float(r / g), 1.0, float(b / g)), f"{setting} ({first.name})"


def decode(path: Path, *, demosaic: str, wb: Sequence[float], time_s: float | None = None,
           sat_margin: float = 0.01) -> Photo:
    """Decode one photo to linear per-second RGB (module doc). ``time_s`` overrides the EXIF exposure time."""
    from objcam.capture.raw import read_ldr, read_raw, read_tiff16
    from objcam.image_io import read_exr

    path = Path(path)
    k = kind(path)
    info = read_exif(path) if k != "exr" else ExposureInfo(None, None, None, None, None, "none")
    if k == "exr":
        t = float(time_s) if time_s is not None else 1.0
        img = read_exr(path)
        rgb = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
        if not np.all(np.isfinite(rgb)):
            raise InputError("image has NaN or infinite values", path, "re-export it")
        return Photo((rgb / t).astype(np.float32), np.zeros(rgb.shape[:2], bool), path, info, t, "exr",
                     tuple(float(x) for x in wb))
    t = exposure_time(path, time_s)
    if k == "raw":
        li = read_raw(path, demosaic=demosaic, wb=list(wb), sat_margin=sat_margin)
        return Photo((li.rgb / np.float32(t)), li.saturated, path, info, t, f"rawpy {demosaic}",
                     tuple(float(x) for x in wb),
                     {"black_level": li.black_level, "white_level": li.white_level,
                      "sensor_shape": list(li.sensor_shape)})
    if k == "tiff":
        li = read_tiff16(path, sat_margin=sat_margin, wb=list(wb))
        return Photo(li.rgb / np.float32(t), li.saturated, path, info, t, "tiff", tuple(float(x) for x in wb))
    img8 = read_ldr(path)
    lin = srgb_to_linear(img8.astype(np.float32) / 255.0)
    return Photo(lin / np.float32(t), np.any(img8 >= 250, axis=2), path, info, t, "srgb", (1.0, 1.0, 1.0))


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), for display-referred JPEG/PNG values in [0, 1]."""
    x = np.asarray(x, np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb8(x: np.ndarray) -> np.ndarray:
    """Linear values (1.0 = white) -> 8-bit sRGB, clipped."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return (y * 255.0 + 0.5).astype(np.uint8)


@dataclass
class Bracket:
    """A merged bracket (or one photo) in per-second units with its validity and what was done."""

    rgb: np.ndarray  # float32 (H, W, 3)
    valid: np.ndarray  # bool (H, W): not saturated in every frame, finite
    record: dict  # merge.json


def merge_folder(paths: Sequence[Path], *, demosaic: str, wb: Sequence[float], times: Sequence[float | None],
                 low: float, high: float, sat_margin: float, what: str) -> Bracket:
    """Merge the photos of one target/probe folder: raws/TIFFs by ``merge_raw_bracket`` (weights proportional to
    exposure time, zero outside [low, high] of the white level or where saturated), JPEG/PNG by OpenCV's Debevec
    response (two or more frames), one EXR as it is. Mixed kinds are an InputError."""
    from objcam.capture.hdr import merge_ldr_bracket, merge_raw_bracket

    paths = [Path(p) for p in paths]
    kinds = {kind(p) for p in paths}
    if len(kinds) > 1 and not kinds <= {"raw", "tiff"}:
        raise InputError(f"{what}: the folder mixes kinds of photo ({', '.join(sorted(kinds))})", paths[0].parent,
                         "keep one bracket per folder: all raws, all TIFFs, all JPEGs, or one EXR")
    k = kinds.pop()
    infos = [read_exif(p) for p in paths] if k != "exr" else []
    rec: dict = {"frames": [p.name for p in paths], "kind": k}
    if k == "exr":
        if len(paths) > 1:
            raise InputError(f"{what}: {len(paths)} EXR files; an EXR is already a merged HDR image",
                             paths[0].parent, "keep one EXR per folder (or give the bracket's raws instead)")
        ph = decode(paths[0], demosaic=demosaic, wb=wb, time_s=times[0])
        valid = np.isfinite(ph.rgb).all(axis=2)
        rec.update({"reader": "exr", "exposure_times_s": [ph.time_s], "weights": "single linear image",
                    "units": "per_second", "n_invalid": int((~valid).sum())})
        return Bracket(ph.rgb, valid, rec)
    if k == "ldr":
        res, resp = merge_ldr_bracket(paths, list(times), units="per_second")
        rec.update({"reader": "opencv CalibrateDebevec/MergeDebevec (relative radiance: JPEG engine's scale and "
                              "white balance)", "response_at_128": float(resp[128].mean())})
    else:
        res = merge_raw_bracket(paths, list(times), demosaic=demosaic, wb=list(wb), low=low, high=high,
                                units="per_second", sat_margin=sat_margin)
        rec.update({"reader": f"rawpy {demosaic}" if k == "raw" else "tiff16",
                    "weights": f"proportional to exposure time, zero where the brightest channel is outside "
                               f"[{low:g}, {high:g}] of the white level or saturated"})
    valid = res.valid & np.isfinite(res.radiance).all(axis=2)
    order = [paths.index(p) for p in res.paths]
    rec.update({
        "frames": [p.name for p in res.paths], "exposure_times_s": list(res.times), "units": "per_second",
        "iso": [infos[i].iso for i in order], "f_number": [infos[i].f_number for i in order],
        "camera": infos[0].camera if infos else None, "exif_reader": infos[0].source if infos else None,
        "focal_length_mm": infos[0].focal_length if infos else None,
        "white_balance": [float(x) for x in wb], "n_invalid": res.n_invalid,
        "saturated_fraction": res.n_invalid / max(1, res.valid.size), "n_fallback": res.n_fallback,
        "frames_used_mean": float(res.frames_used.mean()),
    })
    rgb = np.where(np.isfinite(res.radiance), res.radiance, 0.0).astype(np.float32)
    return Bracket(rgb, valid, rec)


def copy_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """(w, h) of a copy whose longer side is at most ``max_size`` (never upsampled)."""
    s = min(1.0, max_size / max(width, height))
    return max(1, int(round(width * s))), max(1, int(round(height * s)))


def resize(img: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    """Area-average (or nearest, for masks) resize to ``size`` = (w, h); a no-op at the same size."""
    import cv2

    if (img.shape[1], img.shape[0]) == tuple(size):
        return img
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    src = img.astype(np.uint8) if img.dtype == bool else img
    out = cv2.resize(src, size, interpolation=interp)
    return out.astype(bool) if img.dtype == bool else out


def undistort(img: np.ndarray, valid: np.ndarray | None, focal_px: float, distortion: Sequence[float]):
    """Remove OpenCV lens distortion (k1 k2 p1 p2 [k3]) with the pinhole K (focal ``focal_px``, principal point at
    the image centre) kept: the result is the same camera without distortion. Pixels mapping outside the photo
    become 0 and invalid. Returns (image, valid)."""
    import cv2

    h, w = img.shape[:2]
    K = np.array([[focal_px, 0, (w - 1) / 2], [0, focal_px, (h - 1) / 2], [0, 0, 1.0]])
    mx, my = cv2.initUndistortRectifyMap(K, np.asarray(distortion, float), None, K, (w, h), cv2.CV_32FC1)
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    v = inside if valid is None else inside & (cv2.remap(valid.astype(np.uint8), mx, my, cv2.INTER_NEAREST) > 0)
    return out, v
