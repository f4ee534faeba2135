"""Chrome-ball HDR ground truth: the environment map seen from a point, from a mirror ball photographed with an
exposure bracket.

- :mod:`objcam.probe.fit`: find the ball in the merged HDR image and fit its 3D centre to the silhouette
  (perspective-exact cone; the plane z = 0 fixes the distance when the ball rests on it); its last step,
  :mod:`objcam.probe.rim`, a photometric model of the rim for balls >= 300 px in radius; both draw the ball's
  image outline with :mod:`objcam.probe.silhouette`.
- :mod:`objcam.probe.exposure`: bracket checks (saturated everywhere, exposed nowhere, a dim longest frame).
- :mod:`objcam.probe.unwrap` (``unwrap``; the function is not re-exported here, so the module name stays
  importable): the envmap (objcam's lat-long convention) by exact perspective reflection on a fine
  grid, reflectance-corrected, masked, area-averaged to the solve resolution.
- :mod:`objcam.probe.optics`: reflection geometry and the ball's reflectance (calibration factor, Fresnel).
- :mod:`objcam.probe.recover`: bracket checks + fit + unwrap in one call (:func:`recover_probe`).
- :mod:`objcam.probe.measure`: the probe stage's entry point (:func:`~objcam.probe.measure.measure_probe`): the
  ball's reflectance (:mod:`objcam.probe.ball_reflectance`), :func:`recover_probe`, saturated sources, warnings,
  and probe.json's record; :mod:`objcam.probe.merged` reads ingest's merged bracket for it.
- :mod:`objcam.probe.sources`: sources saturated in every frame (direction, lower-bound energy).
- :mod:`objcam.probe.artifact`: the probe stage's files (objcam/stages/probe.py writes them);
  :mod:`objcam.probe.truth`: :func:`~objcam.probe.truth.probe_truth`, the probe as evaluate's ground truth.

Synthetic chrome-ball brackets rendered with Mitsuba (and written in the ingest stage's contract,
:func:`~objcam.synth.probe.write_ingest_probe`) are made by :mod:`objcam.synth.probe`.

Measured accuracy, bilinear sampling (the unwrap now samples bicubically: less blur, see
:mod:`objcam.probe.unwrap`; the probe stage's numbers are in bench/results.md, ``## Chrome-ball probe (issue 5)``)
(synthetic Mitsuba brackets, chromium ball 5 cm at 35 cm, 25 deg elevation, merged 6-8 frame
brackets with shot noise; centre fitted on the plane; probe area-averaged to 32 x 64 against the box-texel truth
area-averaged the same way; per-texel relative RMSE over valid texels, ``objcam.metrics.relative_rmse``; in
brackets: without the 3 x 3 texels around the brightest one):

==============  ====  ============  ===============  ===============  ===============
image / ball    spp   centre err    forest           sunrise          city
==============  ====  ============  ===============  ===============  ===============
256 / 150 px    64    0.04-0.18 mm  0.33-0.46 (0.15) 2.5-3.7 (0.06)   --
1024 / 600 px   64    0.02-0.05 mm  0.078 (0.035)    0.049 (0.018)    0.031 (0.010)
2048 / 1200 px  16    0.015-0.02    0.047 (0.027)    0.080 (0.010)    0.033 (0.006)
==============  ====  ============  ===============  ===============  ===============

The per-texel RMSE of a sunny map is the error on its sun texel (sunrise: 1000x the mean at 32 x 64): 0.3 % of
the sun's energy moves it by 0.08, and the render's Monte Carlo noise on the sun's few pixels is +-5-10 % at
256 px (so 2.5-3.7 there) and 0.3 % at 2048 px. The brightest direction is within 0.1 deg for a sun; forest's
two-texel brightest patch gives 0.2 or 1.97 deg (the metric's 50 % region flips). Without the sun the error is
the pixel footprint's blur (one pixel covers 4 / r_px^2 sr of directions, radially 2 / (r_px cos i) rad), so it
shrinks with the ball's size in pixels: a 5 cm ball at 35 cm through a 50 mm lens on a 24 MP APS-C sensor
spans ~1800 px. The perspective unwrap against the orthographic shortcut, ball 12 cm away: 0.33 against 1.30
(forest, 192 px). Timings (2 cores): fit 1-2 s, unwrap 1 s (512 rows) to 3 s (1024 rows).
"""

from objcam.probe.fit import BallFit, fit_ball
from objcam.probe.optics import Reflectance, fresnel_conductor, reflection_points
from objcam.probe.recover import ProbeResult, ball_mask, check_bracket, recover_probe
from objcam.probe.unwrap import BLIND, CAMERA, OUTSIDE, SATURATED, ProbeEnvmap

__all__ = ["BLIND", "BallFit", "CAMERA", "OUTSIDE", "ProbeEnvmap", "ProbeResult", "Reflectance", "SATURATED",
           "ball_mask", "check_bracket", "fit_ball", "fresnel_conductor", "recover_probe", "reflection_points"]
