"""The end-to-end benchmark's method (bench/e2e_bench.py), checked cheaply on the shared small synthetic photographed
capture: the derived captures (albedo declared, chrome ball dropped) are what ``objcam synth --full`` would write
with those options, on the very same raws; the known-geometry twin states the true mesh and camera and fits the
same merged target pixels as the run from raws. (The benchmark's numbers themselves take ~30 min: bench only.)"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from tests.full_capture import small_full_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return small_full_capture(tmp_path_factory)


def test_derived_capture_same_raws(capture, tmp_path):
    from bench.e2e_bench import derived_capture
    from objcam.schemas.capture import CaptureManifest, TextureAlbedo

    d = derived_capture(capture, tmp_path / "known_albedo", albedo_known=True, probe=False)
    m = CaptureManifest.load(d)
    assert m.albedo.object == pytest.approx(0.6) and isinstance(m.albedo.support, TextureAlbedo)
    truth = json.loads((capture / "truth" / "truth.json").read_text())
    assert m.albedo.support.extent == pytest.approx(truth["albedo"]["support"]["extent"])
    assert (d / m.albedo.support.texture).is_file() and not m.probes and not (d / "probes").exists()
    for p in list((capture / "views").glob("*.dng")) + list((capture / "targets").rglob("*.dng")):
        q = d / p.relative_to(capture)
        assert os.path.samefile(p, q)  # hard links: the same photos, byte for byte
    t2 = json.loads((d / "truth" / "truth.json").read_text())
    assert t2["probes"] == {} and t2["albedo"]["object"]["known"] is True
    # rebuilding it changes nothing (the benchmark's cached runs stay valid)
    before = {p: p.stat().st_mtime_ns for p in d.rglob("*") if p.is_file()}
    derived_capture(capture, tmp_path / "known_albedo", albedo_known=True, probe=False)
    assert {p: p.stat().st_mtime_ns for p in d.rglob("*") if p.is_file()} == before
    # the default flags reproduce the capture's own manifest exactly
    same = derived_capture(capture, tmp_path / "same", albedo_known=False, probe=True)
    assert (same / "capture.toml").read_text() == (capture / "capture.toml").read_text()


def test_known_twin_states_truth_and_fits_the_same_pixels(capture, tmp_path, capsys):
    from bench.e2e_bench import derived_capture, known_capture
    from objcam.camera import Camera
    from objcam.image_io import read_exr
    from objcam.pipeline.cli import main
    from objcam.scene import MeshData, load_mesh

    cap = derived_capture(capture, tmp_path / "cap", albedo_known=True, probe=False)
    work = tmp_path / "work"
    assert main(["ingest", str(cap), "--work", str(work), "-q"]) == 0, capsys.readouterr().err
    twin = known_capture(cap, work, tmp_path / "known")
    assert main(["scene", str(twin), "--work", str(tmp_path / "wk"), "-q"]) == 0, capsys.readouterr().err
    scene = tmp_path / "wk" / "scene"
    targets = json.loads((scene / "targets.json").read_text())
    assert [t["name"] for t in targets] == ["t0"]
    cam = Camera.model_validate(targets[0]["camera"])
    true_cam = Camera.load(capture / "truth" / "cameras" / "targets" / "t0.json")
    assert np.allclose(cam.matrix, true_cam.matrix) and (cam.fx, cam.cx) == (true_cam.fx, true_cam.cx)
    np.testing.assert_array_equal(read_exr(scene / "targets" / "t0" / "image.exr"),
                                  np.maximum(read_exr(work / "ingest" / "targets" / "t0" / "image.exr"), 0))
    import cv2

    v_twin = cv2.imread(str(scene / "targets" / "t0" / "valid.png"), cv2.IMREAD_UNCHANGED) > 127
    v_ingest = cv2.imread(str(work / "ingest" / "targets" / "t0" / "valid.png"), cv2.IMREAD_UNCHANGED) > 127
    assert np.array_equal(v_twin, v_ingest)
    obj = MeshData.load_npz(scene / "object.npz")
    world = load_mesh(capture / "truth" / "object_world.ply")
    assert np.allclose(obj.vertices, world.vertices)
    desc = json.loads((scene / "scene.json").read_text())
    assert desc["albedo_object"]["rgb"] == pytest.approx([0.6] * 3) and desc["albedo_support"]["texture"]
    # evaluate's truth is there
    assert (twin / "truth" / "envmap.exr").is_file() and (twin / "truth" / "albedo_support.exr").is_file()
