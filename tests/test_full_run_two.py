"""A photographed capture with two illuminations, end to end from raw photos: the small synthetic capture of
tests/full_capture.py lit by the forest HDRI at two rotations (0 and 150 degrees, one target bracket and one
chrome ball each), every albedo unknown. Two illuminations constrain the envmaps (one photo could not: see
tests/test_full_run.py), so the solve must not warn, and its envmaps and albedo are held to bounds that broken
answers to the same photos (tests/broken.py) miss."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.full_capture import SMALL_FULL

SETS = ["transport.env_height=8", "transport.downsample=2"]
TARGETS = ("t0_rot0", "t0_rot150")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from objcam.pipeline.cli import main
    from objcam.synth.full import FullSynthParams, synthesize_full

    root = tmp_path_factory.mktemp("two")
    cap = root / "capture"
    synthesize_full(cap, FullSynthParams(**(SMALL_FULL | {"rotations_deg": [0.0, 150.0]})))
    work = root / "work"
    args = ["run", str(cap), "--work", str(work), "-q"]
    for s in SETS:
        args += ["--set", s]
    assert main(args) == 0
    return cap, work


def test_two_illuminations_run_end_to_end_and_constrain_the_envmaps(run):
    cap, work = run
    for stage in ("ingest", "sfm", "geometry", "texture", "probe", "scene", "transport", "solve", "evaluate",
                  "analysis", "report"):
        assert (work / stage / "stage.json").is_file(), stage
    summary = json.loads((work / "solve" / "stage.json").read_text())["summary"]
    assert "WARNING" not in summary, summary
    m = json.loads((work / "evaluate" / "metrics.json").read_text())
    print(json.dumps({t: {k: v for k, v in r.items() if not isinstance(v, dict)} | {"rm": r["baselines"]["row_mean"]}
                      for t, r in m.items()}, indent=1))
    assert sorted(m) == sorted(TARGETS)
    for t in m:
        info = json.loads((work / "solve" / t / "solve.json").read_text())
        assert info["envmap_constrained_by_data"] is True and info["illuminations_in_problem"] == 2
