"""The README's demo figures, checked: ``make demo``'s synth and run (the Makefile's DEMO_SYNTH_ARGS, read from the
Makefile so the test follows it), scored by evaluate, against the numbers README.md states under its figure (SSIM,
relative RMSE, the brightest source's angle), each within a tolerance that allows for the render's and the
transport's Monte Carlo noise on another machine (the scene's seeds are fixed). About a minute on 2 cores."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# SSIM and relative RMSE: the README rounds to 2 digits (0.603 -> 0.60); seeds are fixed, so what moves them is
# code: +-0.03 is a change a reader would see in the figure
SSIM_TOL, RMSE_TOL = 0.03, 0.05


def readme_claims() -> dict[str, float]:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"\(SSIM ([0-9.]+), relative RMSE ([0-9.]+)", text)
    a = re.search(r"brightest\s+source\s+lands\s+within\s+([0-9.]+)\s+degrees", text)
    assert m and a, "README.md's demo caption no longer states SSIM, relative RMSE and the source's angle"
    return {"ssim": float(m.group(1)), "relative_rmse": float(m.group(2)), "angle": float(a.group(1))}


def demo_synth_args() -> list[str]:
    line = next(ln for ln in (ROOT / "Makefile").read_text().splitlines() if ln.startswith("DEMO_SYNTH_ARGS"))
    return shlex.split(line.split("=", 1)[1])


@pytest.mark.slow
def test_the_readme_demo_figures_hold(tmp_path):
    from objcam.pipeline.cli import main

    claims = readme_claims()
    cap = tmp_path / "capture"
    assert main(["synth", str(cap), *demo_synth_args()]) == 0
    assert main(["run", str(cap), "--quiet"]) == 0
    m = json.loads((cap / "objcam" / "evaluate" / "metrics.json").read_text())["t0"]
    assert m["ssim"] == pytest.approx(claims["ssim"], abs=SSIM_TOL), m
    assert m["relative_rmse"] == pytest.approx(claims["relative_rmse"], abs=RMSE_TOL), m
    assert m["brightest_angle_deg"] <= claims["angle"], m  # measured 0.607, 0.638, 1.97 deg (the sun in its own texel)
    # a test of the test: the truth's own flat and row-mean maps (scored by evaluate on the same mask) fall outside
    # the tolerance (measured SSIM 0.15 and 0.24)
    for b in ("constant", "row_mean"):
        assert m["baselines"][b]["ssim"] < claims["ssim"] - SSIM_TOL, (b, m["baselines"][b])
