"""Ingest's merged chrome-ball bracket, read the way :func:`objcam.probe.recover.recover_probe` reads a
:class:`~objcam.capture.hdr.MergeResult`.

Ingest writes per probe ``ingest/probes/<name>/``: ``image.exr`` (exposure-normalised linear RGB), ``valid.png``
(0: saturated in every frame) and ``merge.json`` (the frames, their exposure times, the reader, the white
balance in the data, the pixels with no usable frame). The frames and times let the bracket checks
(:mod:`objcam.probe.exposure`) name the frame to change.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.errors import InputError
from objcam.image_io import read_exr


@dataclass
class MergedProbe:
    """Ingest's merged bracket as objcam.probe.recover reads a MergeResult: radiance (H, W, 3) float32, valid
    (H, W) bool (False: saturated in every frame), frames and exposure times ascending (from merge.json; the
    error messages name them), units ("per_second" for raw/TIFF/EXR brackets; "relative" for JPEG brackets,
    whose levels the exposure checks cannot recover) and the white balance in the data (merge.json's
    ``white_balance``, else none)."""

    radiance: np.ndarray
    valid: np.ndarray
    paths: tuple[Path, ...] = ()
    times: tuple[float, ...] = ()
    info: dict = field(default_factory=dict)
    units: str = "per_second"
    wb: np.ndarray | None = None
    n_fallback: int | None = None  # pixels with no usable frame (merge.json), for the bracket checks


def read_merge_info(path: Path, capture: Path, folder: str) -> tuple[tuple[Path, ...], tuple[float, ...], dict]:
    """Frames and exposure times (ascending) from ingest's merge.json (``frames``: file names in the capture's
    ``folder``, ``exposure_times_s``; records or a ``times`` list are accepted too). Empty when absent."""
    if not path.is_file():
        return (), (), {}
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise InputError("merge.json is not valid JSON", path, "rerun the ingest stage") from None
    if not isinstance(info, dict):
        return (), (), {}
    base = capture / str(info.get("folder") or folder)
    frames = info.get("frames", []) or []
    times = [float(t) for t in (info.get("exposure_times_s") or info.get("times") or [])]
    paths: list[Path] = []
    for f in frames:
        if isinstance(f, dict):
            name = f.get("path") or f.get("source") or f.get("file") or f.get("name")
            t = f.get("time_s", f.get("time"))
            if t is not None and len(times) < len(frames):
                times.append(float(t))
        else:
            name = f
        if name is not None:
            paths.append(base / Path(str(name)).name)
    if len(times) != len(paths) or not paths:
        return tuple(paths), (), info
    order = np.argsort(times, kind="stable")
    return tuple(paths[i] for i in order), tuple(float(times[i]) for i in order), info


def read_merged_probe(folder: Path, capture: Path, name: str, frame_folder: str, cam: Camera) -> MergedProbe:
    """The merged bracket of probe ``name`` in ingest's ``folder`` (``ingest/probes/<name>``), its frames in the
    capture's ``frame_folder``, checked against the camera ``cam`` that took it. InputError (naming the file)
    when the image is missing, of another size than the camera, or not finite, or valid.png is unreadable."""
    import cv2

    img_path = folder / "image.exr"
    if not img_path.is_file():
        raise InputError(f"ingest wrote no merged image for probe {name!r}", img_path,
                         f"check that {frame_folder} holds the ball's photos and rerun the ingest stage")
    img = read_exr(img_path)
    h, w = img.shape[:2]
    if (w, h) != (cam.width, cam.height):
        raise InputError(f"probe image is {w}x{h} but its camera says {cam.width}x{cam.height}", img_path,
                         "give the camera of this photo (at the merged image's size)")
    rgb = img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
    if not np.isfinite(rgb).all():
        raise InputError(f"probe image has {int((~np.isfinite(rgb)).any(axis=2).sum())} NaN or infinite pixels",
                         img_path, "rerun the ingest stage")
    valid = np.ones((h, w), bool)
    vpath = folder / "valid.png"
    if vpath.is_file():
        v = cv2.imread(str(vpath), cv2.IMREAD_UNCHANGED)
        if v is None or v.shape[:2] != (h, w):
            raise InputError("valid.png is unreadable or not the image's size", vpath, "rerun the ingest stage")
        valid = (v.reshape(h, w, -1) > 127).any(axis=2)
    paths, times, info = read_merge_info(folder / "merge.json", capture, frame_folder)
    if not paths:  # no frame list: errors name the merged image
        paths, times = (img_path,), ()
    relative = "opencv" in str(info.get("reader", "")).lower() or info.get("units", "per_second") != "per_second"
    wb = info.get("white_balance")
    wb = np.asarray(wb, np.float32) if isinstance(wb, list) and len(wb) == 3 else None
    n_fb = info.get("n_fallback")
    return MergedProbe(np.ascontiguousarray(np.maximum(rgb, 0), np.float32), valid, paths, times, info,
                       "relative" if relative else "per_second", wb, int(n_fb) if isinstance(n_fb, int) else None)
