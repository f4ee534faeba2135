"""Light at the horizon (issue 22, items 2 and 3), end to end on a small scene path-traced by Mitsuba: a 2-degree
lamp 3 degrees above the horizon over a dim sky, the bunny of known albedo on its plane, one 64 x 64 camera.

The row above the horizon (0-5.6 deg at 32 x 64) is seen at grazing incidence, and the row below it only through
a sliver past the plane's edge (``solve.weak_texels``: excluded, not solved). The lamp must come back in its own
texel's direction, the near-horizon band must keep its energy (the prior's edges to the excluded row once pulled
it to a third of the truth and moved the lamp a row up), and nothing may be put below the horizon."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.envmap import EnvGrid, resample_to_height, read_latlong, write_latlong
from objcam.metrics import angle_deg, brightest_direction
from objcam.pipeline.cli import main

LAMP_ELEVATION, LAMP_AZIMUTH, LAMP_RADIUS = 3.0, 40.0, 1.0  # degrees
SKY, GROUND, LAMP = 0.05, 0.03, 60.0  # radiance: the lamp carries ~6x the sky's power


def lamp_envmap(height: int = 128) -> np.ndarray:
    """(H, 2H, 3) objcam's grid: a dim sky, a darker ground, and a disc lamp."""
    grid = EnvGrid(height)
    d = grid.directions()
    env = np.where(d[..., 2:3] > 0, SKY, GROUND) * np.ones(3)
    e, a = np.radians(LAMP_ELEVATION), np.radians(LAMP_AZIMUTH)
    lamp = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    env[d @ lamp > np.cos(np.radians(LAMP_RADIUS))] = LAMP
    return env.astype(np.float32)


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    root = tmp_path_factory.mktemp("horizon")
    write_latlong(root / "lamp.exr", lamp_envmap())
    cap = root / "capture"
    cams = '[{"width": 64, "height": 64, "elevation_deg": 30}]'
    assert main(["synth", str(cap), "--envmap", str(root / "lamp.exr"), "--object-albedo-known", "true",
                 "--support-albedo-known", "true", "--object-albedo", "0.6", "--support-albedo", "0.6", "--spp", "256", "--cameras", cams]) == 0
    assert main(["run", str(cap), "--until", "evaluate"]) == 0
    work = cap / "objcam"
    est = read_latlong(work / "solve" / "t0" / "envmap.exr")[..., :3].astype(np.float64)
    truth = resample_to_height(read_latlong(root / "lamp.exr")[..., :3].astype(np.float64), est.shape[0])
    return est, truth, work


def band_ratio(est: np.ndarray, truth: np.ndarray, lo: float, hi: float) -> float:
    """Estimate / truth luminance x solid angle over the rows whose centre elevation is in [lo, hi) degrees."""
    grid = EnvGrid(est.shape[0])
    elev = 90.0 - np.degrees(grid.centres()[0][:, 0])
    rows = (elev >= lo) & (elev < hi)
    w = grid.solid_angles()[rows]
    return float((est[rows].mean(-1) * w).sum() / (truth[rows].mean(-1) * w).sum())


def test_the_lamp_three_degrees_up_comes_back_in_its_direction(solved):
    est, truth, work = solved
    err = angle_deg(brightest_direction(est), brightest_direction(truth))
    assert err <= 5.6  # one texel at 32 x 64 (measured 2.8; 4.4 with the prior's edges to the excluded row)
    assert json.loads((work / "evaluate" / "metrics.json").read_text())["t0"]["brightest_angle_deg"] <= 5.6


def test_the_near_horizon_band_keeps_its_energy_and_nothing_goes_below(solved):
    est, truth, _ = solved
    assert 0.67 <= band_ratio(est, truth, 0.0, 10.0) <= 1.5
    # the grazing row alone: measured 0.875; 0.764 with the prior's edges to the excluded row left in
    assert 0.8 <= band_ratio(est, truth, 0.0, 5.7) <= 1.5
    grid = EnvGrid(est.shape[0])
    below = (90.0 - np.degrees(grid.centres()[0][:, 0])) < 0
    assert np.abs(est[below]).max() == 0.0  # the row seen through the sliver is excluded, not solved
