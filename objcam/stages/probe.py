"""Stage ``probe``: chrome-ball HDR ground truth (issue 5).

Applies when the capture lists ``[[probes]]``. Per probe it reads ingest's merged bracket
(``ingest/probes/<name>/image.exr``, ``valid.png``, ``merge.json``: objcam.probe.merged) and the camera that took
it (the manifest's ``camera`` file, else sfm's ``cameras/probes/<name>.json``), then
(:func:`objcam.probe.measure.measure_probe`, through objcam.probe.recover):

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
    envmap_gt.exr           full-resolution lat-long envmap (standard file convention, world frame), linear RGB
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

import time
from pathlib import Path
from typing import Literal

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
# the code whose changes invalidate cached probe artifacts: all of the measurement lives in objcam.probe
CODE_DEPS = ("objcam.probe",)
STEPS = ("load", "fit", "unwrap", "downsample", "write")  # per probe, on the progress bar and in probe.json


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


def _camera(spec: ProbeSpec, capture: Path, upstream: dict[str, Path]) -> tuple[Camera, str, Path]:
    """The camera of probe ``spec``'s photo, where it came from ("manifest" or "sfm") and its file."""
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


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str) -> None:
        pass

    def close(self) -> None:
        pass


class _Steps:
    """One probe's progress: each step's name on the bar as it starts (the first, "load", at creation), and the
    seconds each took (probe.json ``seconds``)."""

    def __init__(self, pb, probe: str):
        self.pb, self.probe = pb, probe
        self.t0 = self.mark = time.perf_counter()
        self.current = STEPS[0]
        self.seconds: dict[str, float] = {}

    def start(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[self.current] = round(now - self.mark, 3)
        self.mark, self.current = now, name
        self.pb.set_postfix_str(f"{self.probe}: {name}")
        self.pb.update(1)

    def totals(self) -> dict[str, float]:
        """The seconds of every step so far, the current one included, and their ``total``."""
        self.seconds[self.current] = round(time.perf_counter() - self.mark, 3)
        return dict(self.seconds, total=round(time.perf_counter() - self.t0, 3))


def _one(spec: ProbeSpec, capture: Path, inputs: StageInputs, params: Params, pb) -> dict:
    """Read probe ``spec``'s camera and merged bracket, measure it, write its folder; returns its probe.json
    record."""
    from objcam.probe.artifact import write_ball_png, write_probe
    from objcam.probe.measure import ProbeSettings, measure_probe
    from objcam.probe.merged import read_merged_probe
    from objcam.probe.silhouette import silhouette_px

    steps = _Steps(pb, spec.name)
    cam, cam_source, cam_path = _camera(spec, capture, inputs.upstream)
    merged = read_merged_probe(inputs.upstream["ingest"] / "probes" / spec.name, capture, spec.name, spec.folder,
                               cam)
    m = measure_probe(merged, cam, spec, ProbeSettings(**params.model_dump()), on_step=steps.start)
    steps.start("write")
    rec = m.record(camera={"source": cam_source, "file": str(cam_path)})
    res, fit = m.result, m.result.fit
    folder = inputs.out / spec.name
    folder.mkdir(parents=True, exist_ok=True)
    sil = silhouette_px(cam, fit.centre_world, spec.diameter / 2, 720)
    write_ball_png(folder / "ball.png", merged.radiance, sil, fit.centre_px, fit.apparent_radius_px)
    rec["seconds"] = steps.totals()  # all but writing the maps
    write_probe(folder, res.probe.envmap, res.probe.flags, res.envmap, res.valid, res.saturated, rec)
    pb.update(1)
    return rec


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
    pb = _NoBar() if inputs.quiet else bar(total=len(STEPS) * len(manifest.probes), desc="probe", unit="step")
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
