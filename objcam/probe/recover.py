"""One call from a merged chrome-ball bracket to the ground-truth envmap: bracket checks, ball fit, unwrap, and
the area-averaged map at the solve resolution.

Bracket checks (:mod:`objcam.probe.exposure`; InputError naming the frame to change): saturated everywhere (the
SHORTEST frame: add shorter exposures) or exposed nowhere (the LONGEST frame: add longer ones), over the image
and then over the ball's pixels; a bracket whose longest frame saturates nowhere on a dim ball is a warning
(``ProbeResult.warnings``). A few saturated pixels (the sun) are expected: they are flagged, their texels marked
SATURATED, and the energy there is a lower bound (``ProbeResult.lower_bound``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from objcam.camera import Camera
from objcam.probe.exposure import MAX_BAD_FRACTION, check_bracket, dim_warning  # noqa: F401 (re-exported)
from objcam.probe.fit import BallFit, fit_ball
from objcam.probe.optics import Reflectance
from objcam.probe.unwrap import ProbeEnvmap, unwrap
from objcam.threads import single_blas_thread


@dataclass
class ProbeResult:
    fit: BallFit
    probe: ProbeEnvmap  # fine grid
    envmap: np.ndarray | None = None  # (h, 2h, 3) area-averaged to solve_height
    valid: np.ndarray | None = None  # (h, 2h) bool
    saturated: np.ndarray | None = None  # (h, 2h) bool: lower bounds
    ball_saturated_fraction: float = 0.0  # of the ball's pixels saturated in every frame
    warnings: list[str] = field(default_factory=list)  # the fit's, and a dim bracket's (objcam.probe.exposure)

    @property
    def lower_bound(self) -> bool:
        return self.probe.lower_bound

    def summary(self) -> dict:
        out = {"fit": self.fit.to_dict(), "probe": self.probe.summary(),
               "ball_saturated_fraction": self.ball_saturated_fraction, "lower_bound": self.lower_bound,
               "warnings": list(self.warnings)}
        if self.valid is not None:
            out["solve_height"] = int(self.valid.shape[0])
            out["valid_texels"] = int(self.valid.sum())
            out["saturated_texels"] = int(self.saturated.sum())
        return out


def fine_height(apparent_radius_px: float, multiple_of: int = 1) -> int:
    """Rows of the fine unwrap grid for a ball of ``apparent_radius_px``: 512, or 1024 once a fine texel would be
    coarser than one image pixel at the ball's centre (2 / r_px rad against pi / rows: r_px > 330), rounded up
    to a multiple of ``multiple_of`` (the solve height it is area-averaged to)."""
    rows = 512 if apparent_radius_px * np.pi / 2 <= 512 else 1024
    m = max(int(multiple_of), 1)
    return -(-rows // m) * m


def ball_mask(camera: Camera, centre, radius: float) -> np.ndarray:
    """(H, W) bool: pixels whose centre ray hits the sphere."""
    vv, uu = np.meshgrid(np.arange(camera.height, dtype=np.float64), np.arange(camera.width, dtype=np.float64),
                         indexing="ij")
    o, d = camera.rays(uu, vv)
    oc = np.asarray(centre, np.float64) - camera.centre
    t = d @ oc
    miss2 = np.sum(oc * oc) - t * t
    return (t > 0) & (miss2 <= radius * radius)


def recover_probe(hdr, camera: Camera, radius: float, *, known_centre=None, rests_on_plane: bool = True,
                  approx_px=None, skip_contact: float = 1.0, height: int | None = None,
                  solve_height: int | None = None, reflectance: Reflectance | None = None,
                  max_incidence_deg: float = 80.0, camera_cone_deg: float = 10.0, min_valid_fraction: float = 0.5,
                  interpolation: str = "cubic", source: str | Path | None = None,
                  on_step: Callable[[str], None] | None = None, use_rim: bool = True,
                  contact_arc: str = "auto") -> ProbeResult:
    """Ground-truth envmap from a chrome ball of ``radius`` metres in ``hdr``: a
    :class:`~objcam.capture.hdr.MergeResult` (bracket checks and saturation flags) or an (H, W, 3) array.

    The fine map is ``height`` rows (default: 512, or 1024 when the ball's apparent radius exceeds 330 px, so
    that a fine texel is no larger than a pixel at the ball's centre); with ``solve_height`` it is also
    area-averaged to that many rows (``height`` must be a multiple). Radiance is in the units of ``hdr`` (a
    MergeResult's ``reference`` units: scene radiance times the longest exposure time, for a synthetic
    bracket). Other arguments: :func:`objcam.probe.fit.fit_ball`, :func:`objcam.probe.unwrap.unwrap`,
    :meth:`objcam.probe.unwrap.ProbeEnvmap.downsample`. ``on_step``: called with "fit", "unwrap", "downsample"
    as each step starts (progress reporting).
    """
    step = on_step or (lambda name: None)
    merge = hdr if hasattr(hdr, "radiance") else None
    if merge is not None:
        check_bracket(merge)
    step("fit")
    with single_blas_thread():  # many small least-squares solves: threads only add overhead
        fit = fit_ball(hdr, camera, radius, known_centre=known_centre, rests_on_plane=rests_on_plane,
                       approx_px=approx_px, skip_contact=skip_contact, source=source, use_rim=use_rim,
                       contact_arc=contact_arc)
    sat_frac = 0.0
    warnings = list(fit.warnings)
    if merge is not None:
        ball = ball_mask(camera, fit.centre_world, radius)
        check_bracket(merge, ball, "the chrome ball")
        sat_frac = float((~np.asarray(merge.valid, bool) & ball).sum() / max(ball.sum(), 1))
        dim = dim_warning(merge, ball)
        if dim:
            warnings.append(dim)
    step("unwrap")
    if height is None:
        height = fine_height(fit.apparent_radius_px, solve_height or 1)
    probe = unwrap(hdr, camera, fit.centre_world, radius, height=height, reflectance=reflectance,
                   max_incidence_deg=max_incidence_deg, camera_cone_deg=camera_cone_deg, interpolation=interpolation)
    res = ProbeResult(fit, probe, ball_saturated_fraction=sat_frac, warnings=warnings)
    if solve_height is not None:
        step("downsample")
        res.envmap, res.valid, res.saturated = probe.downsample(solve_height, min_valid_fraction)
    return res
