"""``objcam synth --full``: the synthetic photographed capture is a valid capture whose raws read back like a
camera's, with the truth it claims (cameras, object pose, clean radiance)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.camera import Camera
from tests.full_capture import SMALL_FULL, small_full_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return small_full_capture(tmp_path_factory)


def test_manifest_validates(capture):
    from objcam.schemas.capture import CaptureManifest

    m = CaptureManifest.load(capture)
    assert m.photographed and m.views is not None and m.views.folder == "views"
    assert m.board is not None and m.board.squares_x == 13
    assert m.camera.white_balance == "camera" and m.camera.demosaic == "superpixel"
    assert [t.name for t in m.targets] == ["t0"] and m.targets[0].folder == "targets/t0"
    assert m.targets[0].camera is None and m.targets[0].image is None
    assert [(p.name, p.diameter, p.centre) for p in m.probes] == [("t0", SMALL_FULL["probe_diameter"],
                                                                  (0.0, 0.0, SMALL_FULL["probe_diameter"] / 2))]
    assert m.scene.object == "object.ply"
    assert len(list((capture / "views").glob("*.dng"))) == SMALL_FULL["n_views"]
    assert len(list((capture / "targets" / "t0").glob("*.dng"))) == SMALL_FULL["bracket_frames"]
    assert len(list((capture / "probes" / "t0").glob("*.dng"))) == SMALL_FULL["probe_bracket_frames"]


def test_dngs_read_back_with_exposure_and_radiance(capture):
    """Every frame's EXIF exposure is the one truth.json states; the superpixel decode of the longest target frame,
    camera white balance applied, divided by its time, is the clean render within noise."""
    import rawpy

    from objcam.capture.exif import read_exif
    from objcam.capture.raw import read_raw
    from objcam.image_io import read_exr

    truth = json.loads((capture / "truth" / "truth.json").read_text())
    frames = truth["targets"]["t0"]["frames"]
    for f in frames:
        info = read_exif(capture / "targets" / "t0" / f["file"])
        assert info.exposure_time == pytest.approx(f["exposure_time_s"], rel=1e-6)
        assert info.iso == 100 and info.f_number == pytest.approx(8.0)
        assert info.focal_length == pytest.approx(11.75 / np.tan(np.radians(SMALL_FULL["fov_deg"]) / 2), abs=0.05)
    times = [f["exposure_time_s"] for f in frames]
    assert times == sorted(times, reverse=True) and times[0] / times[1] == pytest.approx(4.0)
    longest = capture / "targets" / "t0" / frames[0]["file"]
    with rawpy.imread(str(longest)) as r:
        assert r.raw_image_visible.shape == (2 * SMALL_FULL["height"], 2 * SMALL_FULL["width"])
        assert list(r.black_level_per_channel) == [512] * 4 and r.white_level == 16383
        assert r.color_desc == b"RGBG"
    img = read_raw(longest, wb="camera")
    assert img.rgb.shape == (SMALL_FULL["height"], SMALL_FULL["width"], 3)
    np.testing.assert_allclose(img.wb, [2.0, 1.0, 1.5], rtol=1e-4)
    clean = read_exr(capture / truth["targets"]["t0"]["clean_image"])
    per_s = img.rgb / times[0]
    ok = ~img.saturated & (clean.max(axis=2) * times[0] > 0.05)  # well exposed: shot noise ~1-2%
    assert ok.mean() > 0.5
    ratio = per_s[ok] / clean[ok]
    # measured: median 1.000, per-pixel spread ~1.5% (20,000 e- full well, 16 spp render is exact truth here)
    assert np.median(ratio) == pytest.approx(1.0, abs=0.005)
    assert np.percentile(np.abs(ratio - 1), 90) < 0.05
    # a test of the test (tests/broken.py): the raw divided by the next frame's time (4x) misses both bounds
    wrong = img.rgb[ok] / times[1] / clean[ok]
    assert not np.median(wrong) == pytest.approx(1.0, abs=0.005) and not np.percentile(np.abs(wrong - 1), 90) < 0.05


def test_truth_cameras_and_object_pose(capture):
    from objcam.scene import load_mesh

    truth = json.loads((capture / "truth" / "truth.json").read_text())
    views = sorted((capture / "truth" / "cameras" / "views").glob("*.json"))
    assert [p.stem for p in views] == [p.stem for p in sorted((capture / "views").glob("*.dng"))]
    cam = Camera.load(views[0])
    assert (cam.width, cam.height) == (SMALL_FULL["width"], SMALL_FULL["height"])
    tcam = Camera.load(capture / "truth" / "cameras" / "targets" / "t0.json")
    pcam = Camera.load(capture / "truth" / "cameras" / "probes" / "t0.json")
    assert np.allclose(tcam.matrix, pcam.matrix)  # the ball is shot from the target's tripod
    # the target camera looks at the object from target_distance
    assert np.linalg.norm(tcam.centre - [0, 0, 0.02]) == pytest.approx(SMALL_FULL["target_distance"], rel=1e-6)
    # object.ply is in its own frame and millimetres; the stated pose maps it onto the world mesh
    own = load_mesh(capture / "object.ply")
    world = load_mesh(capture / "truth" / "object_world.ply")
    pose = np.asarray(json.loads((capture / "truth" / "object_pose.json").read_text())["world_from_object"])
    mapped = own.vertices.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    assert np.abs(mapped - world.vertices).max() < 1e-5
    lo, hi = own.vertices.min(axis=0), own.vertices.max(axis=0)
    assert hi[2] - lo[2] == pytest.approx(80.0, rel=1e-3)  # 8 cm in millimetres
    assert np.allclose((lo + hi) / 2, 0.0, atol=1e-3)
    assert world.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-7)
    assert truth["probes"]["t0"]["centre"] == [0.0, 0.0, SMALL_FULL["probe_diameter"] / 2]
    assert (capture / truth["envmaps"]["t0"]).is_file()


def test_cli_refuses_options_of_the_other_flavour(tmp_path, capsys):
    from objcam.pipeline.cli import main

    assert main(["synth", str(tmp_path / "x"), "--full", "--spp", "4"]) == 2
    assert "--spp only applies without --full" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "y"), "--n-views", "4"]) == 2
    assert "--n-views only applies with --full" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
