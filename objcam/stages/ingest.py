"""Stage ``ingest``: photos -> linear images (issue 3).

Applies when the capture has photos: a ``[views]`` folder, a target given as a ``folder`` or any ``[[probes]]``.

Artifact folder (``objcam/ingest/``), the contract the sfm, geometry, texture, probe and scene stages read:
    views.json                 list of {name (file stem), source (capture-relative path), width, height,
                               scale (copy size / photo size), exposure {time_s, iso, f_number}, white_balance}
                               (and, additive: photo_width, photo_height, camera, focal_length_mm, reader, saturated_fraction)
    views/<stem>.png           8-bit sRGB copy for SfM (longest side <= views.max_size), undistorted if
                               [camera] distortion is given
    views/<stem>.exr           linear RGB float32 at the same size (raw-linear camera RGB, exposure-normalised
                               to radiance x 1 s), for texture baking
    views_valid/<stem>.png     (additive) 255 = not saturated in the photo, inside the undistorted frame
    targets/<name>/image.exr   linear HDR RGB float32 (merged bracket, exposure-normalised)
    targets/<name>/valid.png   255 = usable (not saturated in every frame, finite)
    targets/<name>/merge.json  frames, exposure times, weights used, saturated fraction, reader used
    targets/<name>/sfm.png     8-bit tonemapped copy of the target at the views' scale, for SfM
    probes/<name>/...          the same four files for every chrome-ball bracket
    ingest.json                (additive) white balance used and where it came from, units, per-image summary

Units ("exposure-normalised"): raw-linear camera RGB in white-level units (black level subtracted, divided by
white - black), times the capture's one white balance, divided by the exposure time in seconds
(``objcam.capture.photos``). ISO and aperture are recorded, not divided out: keep them fixed in a capture (the
summary warns when they differ). Full images (targets, probes) keep the decoded photo's size (superpixel
demosaicing: half the sensor's), so a camera posed by sfm at that size applies to them directly.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.errors import InputError
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import CaptureManifest, try_load

NAME = "ingest"
DEPS: tuple[str, ...] = ()
VERSION = "1"
CODE_DEPS: tuple[str, ...] = ("objcam.capture",)
APPLIES_WHEN = "the capture has photos ([views], a target folder or [[probes]])"


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and m.photographed


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    low: float = Field(0.002, ge=0, lt=1, description="bracket merge: frames whose brightest channel is below "
                       "this fraction of the white level get no weight (noise floor)")
    high: float = Field(0.9, gt=0, le=1, description="bracket merge: ... above this fraction get no weight "
                        "(near saturation)")
    sat_margin: float = Field(0.01, ge=0, lt=0.5, description="a raw sample within this fraction of the range "
                              "below the white level counts as saturated")
    view_percentile: float = Field(99.0, gt=0, le=100, description="the SfM copies of the views share one "
                                   "exposure: the median over views of this percentile maps to white")
    target_percentile: float = Field(99.0, gt=0, le=100, description="SfM copies of targets and probes: their "
                                     "own percentile maps to white")


def _folders(capture: Path, m: CaptureManifest) -> tuple[Path | None, dict[str, Path], dict[str, Path]]:
    views = capture / m.views.folder if m.views is not None else None
    targets = {t.name: capture / t.folder for t in m.targets if t.folder}
    probes = {p.name: capture / p.folder for p in m.probes}
    return views, targets, probes


def input_files(capture: Path) -> list[Path]:
    """capture.toml and every photo this stage reads (their contents key the cache)."""
    from objcam.capture.photos import PHOTO_EXTENSIONS

    capture = Path(capture)
    files = [capture / "capture.toml"]
    m = try_load(capture)
    if m is None:
        return files
    views, targets, probes = _folders(capture, m)
    for folder in ([views] if views else []) + list(targets.values()) + list(probes.values()):
        if folder.is_dir():
            files += sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                            and p.suffix.lower() in PHOTO_EXTENSIONS)
    return files


def _rel(path: Path, capture: Path) -> str:
    try:
        return path.resolve().relative_to(capture.resolve()).as_posix()
    except ValueError:
        return str(path)


def _check_distortion(m: CaptureManifest, capture: Path) -> None:
    d = m.camera.distortion
    if d is None:
        return
    if len(d) not in (4, 5):
        raise InputError(f"[camera] distortion has {len(d)} values", capture / "capture.toml",
                         "give OpenCV's k1, k2, p1, p2 and optionally k3")
    if m.camera.focal_px is None:
        raise InputError("[camera] distortion needs the focal length it was calibrated with", capture / "capture.toml",
                         "add focal_px (pixels of the decoded photo) to [camera]")


def _undistort(img, valid, m: CaptureManifest):
    from objcam.capture.photos import undistort

    if m.camera.distortion is None:
        return img, valid
    # focal_px is in pixels of the decoded photo; a view copy is undistorted before resizing, so no scaling
    return undistort(img, valid, float(m.camera.focal_px), m.camera.distortion)


def _sfm_png(path: Path, rgb: np.ndarray, ref: float) -> None:
    """8-bit sRGB display copy: ``ref`` maps to white."""
    from objcam.capture.photos import linear_to_srgb8
    from objcam.image_io import atomic_write_bytes
    import cv2

    q = linear_to_srgb8(np.maximum(rgb, 0) / max(ref, 1e-30))
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(q[..., ::-1]))
    if not ok:
        raise OSError(f"cannot encode {path}")
    atomic_write_bytes(path, buf.tobytes())


def _percentile(rgb: np.ndarray, q: float) -> float:
    v = np.max(rgb, axis=2)
    v = v[np.isfinite(v) & (v > 0)]
    return float(np.percentile(v, q)) if v.size else 1.0


def _ingest_views(capture: Path, m: CaptureManifest, out: Path, wb, params: Params, progress) -> list[dict]:
    from objcam.capture.photos import copy_size, decode, list_photos, resize, time_override
    from objcam.image_io import read_exr, write_exr, write_png

    folder = capture / m.views.folder
    photos = list_photos(folder, "views")
    stems: dict[str, Path] = {}
    for p in photos:
        if p.stem in stems:
            raise InputError(f"two views named {p.stem!r} ({stems[p.stem].name}, {p.name})", p,
                             "keep one file per photo (e.g. only the raws) in the views folder")
        stems[p.stem] = p
    records, refs = [], []
    for p in photos:
        t_s = time_override(p, m.camera.exposure_times, capture, m.camera.exposure_time)
        ph = decode(p, demosaic=m.camera.demosaic, wb=wb, time_s=t_s, sat_margin=params.sat_margin)
        h, w = ph.rgb.shape[:2]
        img, valid = _undistort(ph.rgb, ~ph.saturated, m)
        size = copy_size(w, h, m.views.max_size)
        img = resize(img, size)
        valid = resize(valid, size, nearest=True)
        write_exr(out / "views" / f"{p.stem}.exr", img)
        write_png(out / "views_valid" / f"{p.stem}.png", valid.astype(np.float64))
        refs.append(_percentile(img, params.view_percentile))
        records.append({"name": p.stem, "source": _rel(p, capture), "width": size[0], "height": size[1],
                        "scale": size[0] / w, "photo_width": w, "photo_height": h,
                        "exposure": {"time_s": ph.time_s, "iso": ph.exposure.iso, "f_number": ph.exposure.f_number},
                        "white_balance": list(ph.wb), "camera": ph.exposure.camera,
                        "focal_length_mm": ph.exposure.focal_length, "reader": ph.reader,
                        "saturated_fraction": float(ph.saturated.mean())})
        progress.update(1)
    # one exposure for every SfM copy (a camera in manual mode), robust to a few odd views
    ref = float(np.median(refs))
    for r in records:
        _sfm_png(out / "views" / f"{r['name']}.png", read_exr(out / "views" / f"{r['name']}.exr")[..., :3], ref)
    return records


def _ingest_bracket(kind: str, name: str, folder: Path, capture: Path, m: CaptureManifest, out: Path, wb,
                    params: Params, progress) -> dict:
    from objcam.capture.photos import copy_size, list_photos, merge_folder, resize, time_override
    from objcam.image_io import atomic_write_text, write_exr, write_png

    what = f"{kind[:-1]} {name}"
    photos = list_photos(folder, what)
    times = [time_override(p, m.camera.exposure_times, capture, m.camera.exposure_time) for p in photos]
    br = merge_folder(photos, demosaic=m.camera.demosaic, wb=wb, times=times, low=params.low, high=params.high,
                      sat_margin=params.sat_margin, what=what)
    rgb, valid = _undistort(br.rgb, br.valid, m)
    if not valid.any():
        raise InputError(f"{what}: every pixel is saturated in every frame", folder,
                         "add shorter exposures to the bracket")
    d = out / kind / name
    write_exr(d / "image.exr", rgb)
    write_png(d / "valid.png", valid.astype(np.float64))
    h, w = rgb.shape[:2]
    size = copy_size(w, h, m.views.max_size if m.views is not None else max(w, h))
    _sfm_png(d / "sfm.png", resize(rgb, size), _percentile(rgb, params.target_percentile))
    rec = dict(br.record)
    rec.update({"name": name, "folder": _rel(folder, capture), "width": w, "height": h,
                "sfm_png": {"width": size[0], "height": size[1], "scale": size[0] / w},
                "undistorted": m.camera.distortion is not None, "n_valid": int(valid.sum())})
    atomic_write_text(d / "merge.json", json.dumps(rec, indent=2))
    progress.update(len(photos))
    return rec


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    from objcam.capture.photos import list_photos, resolve_white_balance
    from objcam.image_io import atomic_write_text
    from objcam.progress import bar

    if params.low >= params.high:
        raise InputError(f"ingest.low ({params.low}) must be below ingest.high ({params.high})", None,
                         "fix the --set values")
    t0 = time.perf_counter()
    capture, out = inputs.capture, inputs.out
    m = CaptureManifest.load(capture)
    _check_distortion(m, capture)
    views, targets, probes = _folders(capture, m)
    # list everything first: an empty or missing folder fails before any slow decoding
    listed = {"views": list_photos(views, "views") if views else []}
    for name, f in targets.items():
        listed[f"targets/{name}"] = list_photos(f, f"target {name}")
    for name, f in probes.items():
        listed[f"probes/{name}"] = list_photos(f, f"probe {name}")
    every = [p for ps in listed.values() for p in ps]
    wb, wb_source = resolve_white_balance(m.camera.white_balance, every)

    progress = bar(total=len(every), desc="ingest", unit="photo")
    try:
        view_recs = _ingest_views(capture, m, out, wb, params, progress) if views else []
        target_recs = {n: _ingest_bracket("targets", n, f, capture, m, out, wb, params, progress)
                       for n, f in targets.items()}
        probe_recs = {n: _ingest_bracket("probes", n, f, capture, m, out, wb, params, progress)
                      for n, f in probes.items()}
    finally:
        progress.close()
    atomic_write_text(out / "views.json", json.dumps(view_recs, indent=2))

    settings = {(r["exposure"]["iso"], r["exposure"]["f_number"]) for r in view_recs}
    for r in list(target_recs.values()) + list(probe_recs.values()):
        settings |= {(i, f) for i, f in zip(r.get("iso", []), r.get("f_number", []))}
    consistent = len(settings) <= 1
    seconds = time.perf_counter() - t0
    metrics = {
        "views": len(view_recs), "targets": len(target_recs), "probes": len(probe_recs), "photos": len(every),
        "white_balance": list(wb), "white_balance_source": wb_source, "units": "decoded value per second",
        "iso_aperture_consistent": consistent,
        "view_size": [view_recs[0]["width"], view_recs[0]["height"]] if view_recs else None,
        "invalid_fraction": {f"{k}/{n}": round(r["n_invalid"] / max(1, r["width"] * r["height"]), 6)
                             for k, recs in (("targets", target_recs), ("probes", probe_recs))
                             for n, r in recs.items()},
        "seconds": round(seconds, 2),
    }
    atomic_write_text(out / "ingest.json", json.dumps(metrics | {
        "targets_detail": target_recs, "probes_detail": probe_recs}, indent=2))
    parts = []
    if view_recs:
        r0 = view_recs[0]
        parts.append(f"{len(view_recs)} views ({r0['photo_width']}x{r0['photo_height']} -> "
                     f"{r0['width']}x{r0['height']})")
    for label, recs in (("target", target_recs), ("probe", probe_recs)):
        if recs:
            frames = sum(len(r["frames"]) for r in recs.values())
            inv = max(r["n_invalid"] / max(1, r["width"] * r["height"]) for r in recs.values())
            parts.append(f"{len(recs)} {label}{'s' if len(recs) > 1 else ''} ({frames} frames, "
                         f"max {inv:.2%} saturated in every frame)")
    summary = "; ".join(parts) + f"; white balance {wb_source}"
    if not consistent:
        summary += "; WARNING: ISO/aperture differ between photos (radiance scales differ)"
    return StageOutputs(metrics=metrics, summary=summary)
