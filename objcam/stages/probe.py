"""Stage ``probe``: chrome-ball HDR ground truth (issue 5).

Applies when the capture lists ``[[probes]]``. Per probe it reads ingest's merged bracket
(``ingest/probes/<name>/image.exr``, ``valid.png``, ``merge.json``) and the camera that took it (the manifest's
``camera`` file, else sfm's ``cameras/probes/<name>.json``), then (objcam.probe.recover):

1. checks the bracket (objcam.probe.exposure; most of the image or of the ball saturated in every frame: an error
   naming the shortest frame; most of it without signal in any frame: an error naming the longest; a longest
   frame that clips nowhere on a dim ball: a warning naming it);
2. fits the ball's 3D centre to its silhouette with the perspective cone, sub-pixel (objcam.probe.fit; the rim
   model of objcam.probe.rim for balls >= 300 px in radius, ``rim``): at the manifest's ``centre`` when given
   (the known 3D centre, e.g. board pose plus radius: used as is; a fit at its height reports how far the photo
   puts the ball, warned about beyond 0.5 mm), else on the plane (centre at z = radius, only x and y free);
3. unwraps the mirror reflection onto a fine world lat-long grid (``height`` rows) by inverse mapping: for each
   texel direction the exact perspective reflection point on the sphere (reflection law, the camera's true
   centre), sampled bicubically, divided by the ball's reflectance at that incidence angle; masks the camera's
   own reflection (``camera_cone_deg``) and the blind spot behind the ball (incidence > ``max_incidence_deg``);
4. area-averages (solid-angle exact) to the solve resolution ``env_height``: a texel is valid when >=
   ``min_valid_fraction`` of its solid angle is valid and none of it saturated.

Reflectance: the manifest's ``reflectance`` (the ball's measured reflectance at normal incidence), else
``default_reflectance``, else chromium's own (measured optical constants, Mitsuba's "Cr": 0.69, 0.65, 0.69 at
normal incidence); the angular shape is ``fresnel`` (default chromium's conductor Fresnel, rising to 1 at
grazing). probe.json records which was used.

Sources saturated in every frame (valid.png 0 on the ball) are flagged: their texels are invalid at the solve
resolution and probe.json lists each with its direction and an energy labelled a LOWER BOUND.

Radiance units: those of ingest's image.exr (exposure-normalised), divided by the reflectance: the same units as
the targets' images when ingest normalised them alike.

Writes per probe ``<name>/`` (see objcam/probe/artifact.py and data_layout.md ``### probe/<name>/``):
    envmap_gt.exr           full-resolution lat-long envmap (objcam convention, world frame), linear RGB
    flags.png               fine mask bits (0 valid, 1 blind, 2 camera, 4 saturated, 8 outside the image)
    envmap_gt_<H>.exr       area-averaged to the solve resolution (H x 2H; H = the transport's env_height)
    valid.png, valid_<H>.png   texels the ball shows (not the camera's reflection, not the blind spot)
    saturated_<H>.png       texels holding a lower bound
    envmap_gt.png, envmap_gt_<H>.png, ball.png   tonemapped views; the ball with its fitted silhouette
    probe.json              ball centre and radius fit, residuals, saturated-source flags, reflectance used
and ``probes.json`` (index: name -> illumination, valid fraction, lower bound), read by
:func:`objcam.probe.truth.probe_truth`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from objcam.camera import Camera
from objcam.errors import InputError
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import CaptureManifest, ProbeSpec, try_load

NAME = "probe"
DEPS: tuple[str, ...] = ("ingest",)
OPTIONAL_DEPS: tuple[str, ...] = ("sfm",)
VERSION = "1"
APPLIES_WHEN = "the capture lists [[probes]]"
CODE_DEPS = ("objcam.probe",)

CHROMIUM = "chromium's measured optical constants (Mitsuba 'Cr'; normal-incidence reflectance 0.69, 0.65, 0.69)"


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and bool(m.probes)


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    env_height: int = Field(32, ge=2, description="solve resolution the probe is area-averaged to (rows; width "
                            "2x): the transport's env_height")
    height: int | None = Field(None, ge=16, le=4096, description="rows of the fine unwrap grid (width 2x); "
                               "default: 512, or 1024 when the ball's apparent radius exceeds 330 px (a fine texel "
                               "no larger than a pixel at the ball's centre), a multiple of env_height")
    max_incidence_deg: float = Field(80.0, gt=0, lt=90, description="blind spot: directions seen at a larger "
                                     "incidence angle (squeezed into the rim) are masked")
    camera_cone_deg: float = Field(10.0, ge=0, lt=90, description="half-angle masked around the direction from "
                                   "the ball to the camera (the camera and photographer reflected)")
    min_valid_fraction: float = Field(0.9, gt=0, le=1, description="a solve-resolution texel is valid when at "
                                      "least this fraction of its solid angle is valid (its value averages the valid "
                                      "part only, so a texel half in the blind spot is no truth for the whole)")
    default_reflectance: float | None = Field(None, gt=0, le=1, description="normal-incidence reflectance when "
                                              "the manifest gives none; default: chromium's own")
    fresnel: Literal["conductor", "schlick", "none"] = Field("conductor", description="angular shape of the "
                                                             "reflectance (conductor: chromium's exact Fresnel)")
    interpolation: Literal["cubic", "linear"] = Field("cubic", description="image sampling of the unwrap")
    rim: bool = Field(True, description="refine the ball's centre with the rim model (objcam.probe.rim) when its "
                      "apparent radius is >= 300 px; false: the edge fit alone")
    contact_arc: Literal["auto", "fit", "skip"] = Field("auto", description="the silhouette's arc against the "
                                                        "support next to the contact point (contact shadow): fitted "
                                                        "when its edges agree with the rest (auto), always, or never")

    @model_validator(mode="after")
    def _multiple(self):
        if self.height is not None and self.height % self.env_height:
            raise ValueError(f"height {self.height} must be a multiple of env_height {self.env_height}")
        return self


def input_files(capture: Path) -> list[Path]:
    """Capture files this stage reads: the manifest and the probes' camera files (ingest's images key the cache
    through the ingest stage's key)."""
    capture = Path(capture)
    files = [capture / "capture.toml"]
    m = try_load(capture)
    if m is not None:
        files += [capture / p.camera for p in m.probes if p.camera is not None and (capture / p.camera).is_file()]
    return files


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


def _merge_info(path: Path, capture: Path, folder: str) -> tuple[tuple[Path, ...], tuple[float, ...], dict]:
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


def _camera(spec: ProbeSpec, capture: Path, upstream: dict[str, Path]) -> tuple[Camera, str, Path]:
    if spec.camera is not None:
        path = capture / spec.camera
        return Camera.load(path), "manifest", path
    if "sfm" in upstream:
        path = upstream["sfm"] / "cameras" / "probes" / f"{spec.name}.json"
        if not path.is_file():
            raise InputError(f"structure from motion could not pose probe {spec.name!r}", capture / spec.folder,
                             "see objcam/sfm/report.json; photograph the ball with more of the board in view, or "
                             "give the probe's camera file in capture.toml")
        return Camera.load(path), "sfm", path
    raise InputError(f"probe {spec.name!r} has no camera", capture / "capture.toml",
                     "give [[probes]] camera (a camera JSON, see data_layout.md), or [views] for structure from "
                     "motion to pose it")


def _load_merged(spec: ProbeSpec, capture: Path, upstream: dict[str, Path], cam: Camera) -> MergedProbe:
    import cv2

    from objcam.image_io import read_exr

    folder = upstream["ingest"] / "probes" / spec.name
    img_path = folder / "image.exr"
    if not img_path.is_file():
        raise InputError(f"ingest wrote no merged image for probe {spec.name!r}", img_path,
                         f"check that {spec.folder} holds the ball's photos and rerun the ingest stage")
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
    paths, times, info = _merge_info(folder / "merge.json", capture, spec.folder)
    if not paths:  # no frame list: errors name the merged image
        paths, times = (img_path,), ()
    relative = "opencv" in str(info.get("reader", "")).lower() or info.get("units", "per_second") != "per_second"
    wb = info.get("white_balance")
    wb = np.asarray(wb, np.float32) if isinstance(wb, list) and len(wb) == 3 else None
    n_fb = info.get("n_fallback")
    return MergedProbe(np.ascontiguousarray(np.maximum(rgb, 0), np.float32), valid, paths, times, info,
                       "relative" if relative else "per_second", wb, int(n_fb) if isinstance(n_fb, int) else None)


def _reflectance(spec: ProbeSpec, params: Params):
    from objcam.probe.optics import Reflectance

    if spec.reflectance is not None:
        value, source = spec.reflectance, "manifest (capture.toml [[probes]] reflectance)"
    elif params.default_reflectance is not None:
        value, source = params.default_reflectance, "probe.default_reflectance"
    else:
        value, source = None, "default: " + CHROMIUM
    if value is None and params.fresnel != "conductor":
        value = tuple(float(x) for x in Reflectance(None, "conductor").f0())  # chromium's F0 with another shape
    refl = Reflectance(value, params.fresnel)
    note = {"conductor": "Fresnel: chromium's conductor curve"
                         + (" remapped to the given normal-incidence value" if value is not None else "")
                         + " (flat to ~40 deg, a dip near 75 deg, 1 at grazing)",
            "schlick": "Fresnel: Schlick's approximation (no conductor dip; up to 0.19 high near 80 deg)",
            "none": "no Fresnel: constant reflectance at every incidence angle"}[params.fresnel]
    return refl, dict(refl.to_dict(), source=source, f0=refl.f0().tolist(), note=note)


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str) -> None:
        pass

    def close(self) -> None:
        pass


def _one(spec: ProbeSpec, capture: Path, inputs: StageInputs, params: Params, pb) -> dict:
    from objcam.probe.artifact import write_ball_png, write_probe
    from objcam.probe.fit import silhouette_px
    from objcam.probe.recover import recover_probe
    from objcam.probe.sources import LOWER_BOUND_LABEL, saturated_sources

    t0 = time.perf_counter()
    cam, cam_source, cam_path = _camera(spec, capture, inputs.upstream)
    merged = _load_merged(spec, capture, inputs.upstream, cam)
    refl, refl_rec = _reflectance(spec, params)
    radius = spec.diameter / 2
    source = merged.paths[-1]  # the longest frame (or the merged image): what fit errors name
    times: dict[str, float] = {}
    mark = [t0, "load"]

    def step(name: str) -> None:
        now = time.perf_counter()
        times[mark[1]] = round(now - mark[0], 3)
        mark[:] = [now, name]
        pb.set_postfix_str(f"{spec.name}: {name}")
        pb.update(1)

    res = recover_probe(merged, cam, radius, known_centre=spec.centre, rests_on_plane=spec.centre is None,
                        height=params.height, solve_height=params.env_height, reflectance=refl,
                        max_incidence_deg=params.max_incidence_deg, camera_cone_deg=params.camera_cone_deg,
                        min_valid_fraction=params.min_valid_fraction, interpolation=params.interpolation,
                        source=source, on_step=step, use_rim=params.rim, contact_arc=params.contact_arc)
    step("write")
    fit, probe = res.fit, res.probe
    sources = saturated_sources(probe)
    ball_sat_px = int(round(res.ball_saturated_fraction * np.pi * fit.apparent_radius_px ** 2))
    warnings = list(res.warnings)
    if res.lower_bound:
        warnings.append(f"{len(sources)} source(s) saturated in every frame of the bracket: their texels are "
                        "invalid and their energy is a lower bound")
    rec = {
        "name": spec.name, "illumination": spec.illumination_name, "folder": spec.folder,
        "source": str(source), "camera": {"source": cam_source, "file": str(cam_path)},
        "diameter": spec.diameter,
        "centre_source": "manifest" if spec.centre is not None else "fitted on the plane z = 0 (centre at z = radius)",
        "fit": fit.to_dict(),
        "reflectance": refl_rec,
        "fine": dict(probe.summary(), height=int(probe.flags.shape[0])),
        "env_height": params.env_height, "min_valid_fraction": params.min_valid_fraction,
        "valid_texels": int(res.valid.sum()),
        "valid_fraction_solid_angle": _valid_fraction(res.valid),
        "masks": {"max_incidence_deg": params.max_incidence_deg, "camera_cone_deg": params.camera_cone_deg},
        "saturation": {"ball_saturated_fraction": res.ball_saturated_fraction, "ball_saturated_pixels": ball_sat_px,
                       "lower_bound": res.lower_bound, "saturated_texels": int(res.saturated.sum()),
                       "sources": sources, "label": LOWER_BOUND_LABEL if res.lower_bound else None},
        "units": "radiance in the units of ingest's image.exr (exposure-normalised), divided by the ball's "
                 "reflectance",
        "merge": {"frames": [str(p) for p in merged.paths], "times": list(merged.times)},
        "interpolation": params.interpolation,
        "warnings": warnings,
    }
    folder = inputs.out / spec.name
    folder.mkdir(parents=True, exist_ok=True)
    sil = silhouette_px(cam, fit.centre_world, radius, 720)
    write_ball_png(folder / "ball.png", merged.radiance, sil, fit.centre_px, fit.apparent_radius_px)
    times[mark[1]] = round(time.perf_counter() - mark[0], 3)
    rec["seconds"] = dict(times, total=round(time.perf_counter() - t0, 3))  # all but writing the maps
    write_probe(folder, probe.envmap, probe.flags, res.envmap, res.valid, res.saturated, rec)
    pb.update(1)
    return rec


def _valid_fraction(valid: np.ndarray) -> float:
    from objcam.envmap import EnvGrid

    w = EnvGrid(valid.shape[0]).solid_angles()
    return float((w * valid).sum() / w.sum())


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    from objcam.probe.artifact import write_index
    from objcam.progress import bar

    capture = Path(inputs.capture)
    manifest = CaptureManifest.load(capture)
    if not manifest.probes:
        raise InputError("capture.toml lists no [[probes]]", capture / "capture.toml",
                         "add a [[probes]] entry for each chrome-ball bracket")
    if "ingest" not in inputs.upstream:
        raise InputError("the probe stage needs the ingest stage's merged images", capture / "capture.toml",
                         "run the ingest stage first")
    steps = 5  # load, fit, unwrap, downsample, write
    pb = _NoBar() if inputs.quiet else bar(total=steps * len(manifest.probes), desc="probe", unit="step")
    records = {}
    try:
        for spec in manifest.probes:
            records[spec.name] = _one(spec, capture, inputs, params, pb)
    finally:
        pb.close()
    write_index(inputs.out, params.env_height, {
        n: {"illumination": r["illumination"], "folder": n, "valid_fraction_solid_angle": r["valid_fraction_solid_angle"],
            "lower_bound": r["saturation"]["lower_bound"]} for n, r in records.items()})
    metrics = {n: {"centre": r["fit"]["centre_world"], "residual_px": r["fit"]["residual_px"],
                   "apparent_radius_px": r["fit"]["apparent_radius_px"], "valid_texels": r["valid_texels"],
                   "valid_fraction_solid_angle": r["valid_fraction_solid_angle"],
                   "lower_bound": r["saturation"]["lower_bound"], "warnings": len(r["warnings"])}
               for n, r in records.items()}
    parts = []
    for n, r in records.items():
        f = r["fit"]
        s = (f"{n}: ball r {f['apparent_radius_px']:.0f} px, edge rms {f['residual_px']:.2f} px, "
             f"{100 * r['valid_fraction_solid_angle']:.0f}% of the sphere valid at {params.env_height} rows")
        if r["saturation"]["lower_bound"]:
            s += ", SATURATED source (lower bound)"
        if r["warnings"]:
            s += f", {len(r['warnings'])} warning(s)"
        parts.append(s)
    return StageOutputs(metrics={"probes": metrics}, summary="; ".join(parts))
