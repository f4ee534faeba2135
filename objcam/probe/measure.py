"""The probe stage's entry point: one chrome ball's merged bracket in, everything probe.json says about it out.

:func:`measure_probe` runs, in order:

1. :func:`~objcam.probe.ball_reflectance.choose_reflectance`: the manifest's reflectance, the stage's default,
   or chromium's;
2. :func:`~objcam.probe.recover.recover_probe`: bracket checks, ball fit, unwrap on the fine grid, area average
   to the solve resolution;
3. :func:`~objcam.probe.sources.saturated_sources`: the sources saturated in every frame (lower bounds);
4. the warnings (the fit's, a dim bracket's, saturated sources) and the valid fraction of the sphere.

:meth:`ProbeMeasurement.record` is the probe.json record; the stage (objcam/stages/probe.py) writes it with the
maps (:func:`objcam.probe.artifact.write_probe`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from objcam.camera import Camera
from objcam.envmap import EnvGrid
from objcam.probe.ball_reflectance import choose_reflectance
from objcam.probe.merged import MergedProbe
from objcam.probe.recover import ProbeResult, recover_probe
from objcam.probe.sources import LOWER_BOUND_LABEL, saturated_sources
from objcam.schemas.capture import ProbeSpec

CENTRE_ON_PLANE = "fitted on the plane z = 0 (centre at z = radius)"
UNITS = "radiance in the units of ingest's image.exr (exposure-normalised), divided by the ball's reflectance"


@dataclass(frozen=True)
class ProbeSettings:
    """The probe stage's parameters (their defaults and meanings: ``Params`` in objcam/stages/probe.py)."""

    env_height: int  # solve resolution (rows) the fine map is area-averaged to
    height: int | None  # rows of the fine unwrap grid (None: from the ball's apparent size)
    max_incidence_deg: float
    camera_cone_deg: float
    min_valid_fraction: float
    default_reflectance: float | None
    fresnel: str  # "conductor", "schlick" or "none"
    interpolation: str  # "cubic" or "linear"
    rim: bool
    contact_arc: str  # "auto", "fit" or "skip"


@dataclass
class ProbeMeasurement:
    """What :func:`measure_probe` found for one probe."""

    spec: ProbeSpec
    merged: MergedProbe
    settings: ProbeSettings
    result: ProbeResult  # fit, fine map, and the maps at settings.env_height
    reflectance: dict  # choose_reflectance's record
    sources: list[dict]  # saturated sources, brightest first
    warnings: list[str]
    valid_fraction: float  # of the sphere's solid angle valid at settings.env_height

    @property
    def source(self) -> Path:
        """The file errors and probe.json name: the bracket's longest frame, or the merged image."""
        return self.merged.paths[-1]

    def record(self, camera: dict) -> dict:
        """probe.json's record (without the stage's timings); ``camera``: where the camera came from
        (``source``, ``file``)."""
        spec, s, res = self.spec, self.settings, self.result
        fit, probe = res.fit, res.probe
        ball_sat_px = int(round(res.ball_saturated_fraction * np.pi * fit.apparent_radius_px ** 2))
        return {
            "name": spec.name, "illumination": spec.illumination_name, "folder": spec.folder,
            "source": str(self.source), "camera": camera,
            "diameter": spec.diameter,
            "centre_source": "manifest" if spec.centre is not None else CENTRE_ON_PLANE,
            "fit": fit.to_dict(),
            "reflectance": self.reflectance,
            "fine": dict(probe.summary(), height=int(probe.flags.shape[0])),
            "env_height": s.env_height, "min_valid_fraction": s.min_valid_fraction,
            "valid_texels": int(res.valid.sum()),
            "valid_fraction_solid_angle": self.valid_fraction,
            "masks": {"max_incidence_deg": s.max_incidence_deg, "camera_cone_deg": s.camera_cone_deg},
            "saturation": {"ball_saturated_fraction": res.ball_saturated_fraction,
                           "ball_saturated_pixels": ball_sat_px, "lower_bound": res.lower_bound,
                           "saturated_texels": int(res.saturated.sum()), "sources": self.sources,
                           "label": LOWER_BOUND_LABEL if res.lower_bound else None},
            "units": UNITS,
            "merge": {"frames": [str(p) for p in self.merged.paths], "times": list(self.merged.times)},
            "interpolation": s.interpolation,
            "warnings": self.warnings,
        }


def measure_probe(merged: MergedProbe, camera: Camera, spec: ProbeSpec, settings: ProbeSettings,
                  on_step: Callable[[str], None] | None = None) -> ProbeMeasurement:
    """Measure the probe ``spec`` from its merged bracket ``merged`` taken by ``camera``: the steps of the module
    doc. ``on_step``: called with "fit", "unwrap", "downsample" as each step of the recovery starts (progress).
    Raises InputError (a bad bracket, no ball, two balls, a ball cut by the image edge), naming the longest
    frame."""
    reflectance, reflectance_record = choose_reflectance(spec.reflectance, settings.default_reflectance,
                                                         settings.fresnel)
    res = recover_probe(merged, camera, spec.diameter / 2, known_centre=spec.centre,
                        rests_on_plane=spec.centre is None, height=settings.height,
                        solve_height=settings.env_height, reflectance=reflectance,
                        max_incidence_deg=settings.max_incidence_deg, camera_cone_deg=settings.camera_cone_deg,
                        min_valid_fraction=settings.min_valid_fraction, interpolation=settings.interpolation,
                        source=merged.paths[-1], on_step=on_step, use_rim=settings.rim,
                        contact_arc=settings.contact_arc)
    sources = saturated_sources(res.probe)
    return ProbeMeasurement(spec, merged, settings, res, reflectance_record, sources,
                            _warnings(res, len(sources)), valid_solid_angle_fraction(res.valid))


def _warnings(res: ProbeResult, n_sources: int) -> list[str]:
    """The recovery's warnings (the fit's, a dim bracket's), then one for sources saturated in every frame."""
    warnings = list(res.warnings)
    if res.lower_bound:
        warnings.append(f"{n_sources} source(s) saturated in every frame of the bracket: their texels are "
                        "invalid and their energy is a lower bound")
    return warnings


def valid_solid_angle_fraction(valid: np.ndarray) -> float:
    """Fraction of the sphere's solid angle that the lat-long mask ``valid`` (H, 2H) bool covers."""
    w = EnvGrid(valid.shape[0]).solid_angles()
    return float((w * valid).sum() / w.sum())
