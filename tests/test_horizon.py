"""Light at the horizon (issue 22, items 2 and 3), end to end on a small scene path-traced by Mitsuba: a 2-degree
lamp 3 degrees above the horizon over a dim sky, the bunny of known albedo on its plane, one 64 x 64 camera.

The row above the horizon (0-5.6 deg at 32 x 64) is seen at grazing incidence, and the row below it only through
a sliver past the plane's edge (``solve.weak_texels``: excluded, not solved). The lamp must come back in its own
texel's direction, the near-horizon band must keep its energy (the prior's edges to the excluded row once pulled
it to a third of the truth and moved the lamp a row up), and nothing may be put below the horizon. Every bound is
also run on broken answers to the same scene, which must miss it (tests/broken.py: a flat sky, the estimate turned
or twice as bright, a solve drowned in its prior, the weak row solved)."""

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


# The bounds of this scene, each between the default's measured value and the broken answers'
# (test_a_broken_answer_fails_the_bounds; measured: default / flat sky / turned 90 deg / ls=1e6 / weak_texels=keep)
LAMP_DEG = 5.6  # one texel at 32 x 64: 2.8 / 87 / 87 / 87 / 98 (4.4 with the prior's edges to the excluded row)
BAND = (0.67, 1.5)  # 0-10 deg energy over the truth's: 1.02 / 0.56 / 1.02 / 0.47 / 1.01; twice as bright 2.05
# the grazing row alone: 0.87 / 0.37 / 0.87 / 0.31 / 0.81; 0.764 with the prior's edges to the excluded row left in
GRAZING = (0.8, 1.5)


def missed_bounds(est: np.ndarray, truth: np.ndarray, evaluated: dict | None = None) -> list[str]:
    """The bounds (above) that the estimate ``est`` (H, 2H, 3) misses against ``truth``; with ``evaluated`` (the
    evaluate stage's metrics of the target) its brightest-light angle too. "below": any energy put below the
    horizon (the row seen through the sliver must be excluded, not solved)."""
    err = angle_deg(brightest_direction(est), brightest_direction(truth))
    band, grazing = band_ratio(est, truth, 0.0, 10.0), band_ratio(est, truth, 0.0, 5.7)
    grid = EnvGrid(est.shape[0])
    below = (90.0 - np.degrees(grid.centres()[0][:, 0])) < 0
    print("horizon: lamp", err, "band", band, "grazing", grazing, "below", np.abs(est[below]).max())
    missed = [] if err <= LAMP_DEG else ["lamp"]
    if evaluated is not None and not evaluated["brightest_angle_deg"] <= LAMP_DEG:
        missed.append("evaluated lamp")
    missed += [] if BAND[0] <= band <= BAND[1] else ["band"]
    missed += [] if GRAZING[0] <= grazing <= GRAZING[1] else ["grazing"]
    return missed + ([] if np.abs(est[below]).max() == 0.0 else ["below"])


def evaluated(work) -> dict:
    return json.loads((work / "evaluate" / "metrics.json").read_text())["t0"]


def test_the_lamp_three_degrees_up_comes_back_in_its_direction(solved):
    """Broken variants (test_a_broken_answer_fails_the_bounds): a flat sky, the estimate turned 90 degrees,
    solve.ls=1e6, solve.weak_texels=keep."""
    est, truth, work = solved
    missed = missed_bounds(est, truth, evaluated(work))
    assert not {"lamp", "evaluated lamp"} & set(missed), missed


def test_the_near_horizon_band_keeps_its_energy_and_nothing_goes_below(solved):
    """Broken variants (test_a_broken_answer_fails_the_bounds): a flat sky and solve.ls=1e6 (too little in the
    band), the estimate twice as bright (too much), solve.weak_texels=keep (energy below the horizon)."""
    est, truth, _ = solved
    missed = missed_bounds(est, truth)
    assert not {"band", "grazing", "below"} & set(missed), missed


# (broken answer, the bounds it must miss at least one of; measured above)
BROKEN = {
    "flat sky of the truth's mean": ("lamp", "band", "grazing"),
    "estimate turned 90 degrees": ("lamp",),
    "estimate twice as bright": ("band", "grazing"),
    "solve.ls=1e6": ("lamp", "evaluated lamp", "band", "grazing"),
    "solve.weak_texels=keep": ("lamp", "evaluated lamp", "below"),
}


@pytest.mark.parametrize("broken", list(BROKEN))
def test_a_broken_answer_fails_the_bounds(solved, tmp_path, broken):
    """A test of the test (tests/broken.py): the bounds above, run on a broken answer to the same scene (reruns
    only the solve and evaluate, ~2 s), are missed."""
    from tests.broken import read_envmap, rerun, rotated, truth_constant

    est, truth, work = solved
    _, mask = read_envmap(work)
    ev = None
    if broken.startswith("flat"):
        est = truth_constant(truth, mask)
    elif broken.startswith("estimate turned"):
        est = rotated(est, mask, 90.0)
    elif broken.startswith("estimate twice"):
        est = 2.0 * est
    else:
        w = rerun(work.parent, work, tmp_path / "work", [broken], until="evaluate")
        est, ev = read_envmap(w)[0], evaluated(w)
    missed = missed_bounds(est, truth, ev)
    assert set(BROKEN[broken]) & set(missed), (broken, missed)
