"""A photographed capture with two illuminations, end to end from raw photos: the small synthetic capture of
tests/full_capture.py lit by the forest HDRI at two rotations (0 and 150 degrees, one target bracket and one
chrome ball each, the target camera on one tripod), every albedo unknown.

Found by this test (issue 28): SfM poses each target photo on its own, so the two tripod shots come out as two
cameras 0.36 mm and 0.06 degrees apart (about 0.3 px here); the transport builds an A for each, the solve groups
targets by camera, and each illumination becomes a problem of its own with one photo and every albedo unknown --
unconstrained, and the solve says so (telling the user to photograph two illuminations, which they did). The test
of the constraint is kept as a strict xfail until targets of one tripod position share one camera.

Also found: the same capture without its chrome balls fails at the geometry stage ("the object mesh's outline does
not match the photographed object's silhouettes (only 46% ...)"): the known-mesh registration refines only its two
best coarse poses (geometry.registration.starts = 2), and on that hull both are the bunny turned 180 degrees
(yaw 210 against the true 30, 2.3 mm RMS against 0.9); with starts = 6 it finds the right pose (84% agreement). The
chrome balls add two SfM images, which moves the hull enough for the right pose to be among the two. This test keeps
the balls so that it runs end to end on the defaults."""

from __future__ import annotations

import json

import pytest

from tests.full_capture import SMALL_FULL

SETS = ["transport.env_height=8", "transport.downsample=4"]
TARGETS = ("rot0", "rot150")


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


def test_two_illuminations_run_end_to_end(run):
    cap, work = run
    for stage in ("ingest", "sfm", "geometry", "texture", "probe", "scene", "transport", "solve", "evaluate",
                  "analysis", "report"):
        assert (work / stage / "stage.json").is_file(), stage
    recs = json.loads((work / "scene" / "targets.json").read_text())
    assert [r["name"] for r in recs] == list(TARGETS) and {r["radiometry"] for r in recs} == {"relative"}
    m = json.loads((work / "evaluate" / "metrics.json").read_text())
    assert sorted(m) == sorted(TARGETS)
    for t, r in m.items():
        assert r["truth_source"] == "truth" and set(r["baselines"]) == {"constant", "row_mean"}, t
        # the truth of each target is its own rotation of the HDRI
        assert r["truth_file"].endswith(f"{t}/envmap.exr") or t in r["truth_file"], r["truth_file"]
    # what the solve did with them is said, not hidden: either one problem (constrained) or a warning per target
    summary = json.loads((work / "solve" / "stage.json").read_text())["summary"]
    infos = {t: json.loads((work / "solve" / t / "solve.json").read_text()) for t in TARGETS}
    for t, info in infos.items():
        assert info["envmap_constrained_by_data"] or summary.startswith("WARNING"), (t, summary)


@pytest.mark.xfail(strict=True, reason="SfM poses each tripod shot on its own: two cameras 0.3 px apart, so the "
                   "illuminations are not solved together (see the module docstring)")
def test_two_illuminations_share_the_camera_and_constrain_the_envmaps(run):
    cap, work = run
    assert json.loads((work / "transport" / "stage.json").read_text())["metrics"]["cameras"] == 1
    for t in TARGETS:
        info = json.loads((work / "solve" / t / "solve.json").read_text())
        assert info["envmap_constrained_by_data"] is True and info["illuminations_in_problem"] == 2, t
