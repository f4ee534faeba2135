"""Stage ``sfm`` (after ``ingest``) on a small synthetic photographed capture from raws: every view, the target and
the chrome-ball photo are posed in the world frame against truth, at the sizes of ingest's images, with a graded
report and a COLMAP model on disk; the no-board frame (plane + object height); a wrong board is one clear line."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from objcam.camera import Camera
from tests.full_capture import SMALL_FULL, small_full_capture


@pytest.fixture(scope="module")
def sfm_run(tmp_path_factory):
    """`objcam sfm CAPTURE --work WORK` on the shared capture: (capture, work, exit code, stderr)."""
    import contextlib
    import io

    from objcam.pipeline.cli import main

    cap = small_full_capture(tmp_path_factory)
    work = tmp_path_factory.mktemp("sfm_stage_work")
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(["sfm", str(cap), "--work", str(work), "-q"])
    return cap, work, rc, err.getvalue()


def _errors(cap, work, kind):
    from objcam.sfm.align import camera_difference

    out = {}
    for p in sorted((cap / "truth" / "cameras" / kind).glob("*.json")):
        est = work / "sfm" / "cameras" / kind / p.name
        assert est.is_file(), est
        e, t = Camera.load(est), Camera.load(p)
        d, a = camera_difference(e, t)
        out[p.stem] = (d * 1000, a, e, t)
    return out


def test_cameras_match_truth(sfm_run):
    cap, work, rc, err = sfm_run
    assert rc == 0, err
    views = _errors(cap, work, "views")
    assert len(views) == SMALL_FULL["n_views"]  # every view registered
    c = np.array([v[0] for v in views.values()])
    r = np.array([v[1] for v in views.values()])
    # 320 x 240, 16 spp, raw noise: measured mean 1.9 mm / 0.22 deg, max 4.0 mm / 0.56 deg (the issue's 0.5 mm /
    # 0.05 deg is for 24 views at 800 x 600; see the report for that measurement)
    assert c.mean() < 3.0 and c.max() < 6.0, c
    assert r.mean() < 0.35 and r.max() < 0.8, r
    for name, (d, a, e, t) in views.items():
        assert (e.width, e.height) == (t.width, t.height) and (e.cx, e.cy) == (t.cx, t.cy)
        assert abs(e.fx / t.fx - 1) < 0.01
    # the target and the chrome ball: measured 0.85 mm / 0.07 deg and 1.1 mm / 0.13 deg
    for kind in ("targets", "probes"):
        (d, a, e, t), = _errors(cap, work, kind).values()
        assert d < 2.5 and a < 0.3, (kind, d, a)
        assert (e.width, e.height) == (t.width, t.height) and abs(e.cx - t.cx) < 1e-9 and abs(e.fx / t.fx - 1) < 0.01
        # the camera fits ingest's full image, which the scene and probe stages read with it
        from objcam.image_io import read_exr

        img = read_exr(work / "ingest" / kind / "t0" / "image.exr")
        assert img.shape[:2] == (e.height, e.width)


@pytest.mark.parametrize("broken", ["scaled 1% (a misread square size)", "turned 0.5 degree about the vertical",
                                    "shifted 3 mm"])
def test_a_broken_alignment_fails_the_camera_bounds(sfm_run, broken):
    """A test of the test (tests/broken.py): the stage's cameras carried by a broken alignment to the board
    (tests/test_sfm.py's) miss the bounds of test_cameras_match_truth (measured, views' mean centre / rotation error
    and the target's: 6.1 mm / 0.21 deg, 5.4 mm scaled; 3.0 mm / 0.52 deg, 2.9 mm / 0.46 deg turned; 3.6 mm / 0.21 deg,
    2.8 mm shifted; bounds 3.0 mm / 0.35 deg, target 2.5 mm / 0.3 deg)."""
    from objcam.sfm.align import camera_difference
    from tests.test_sfm import broken_alignments, moved

    cap, work, _, _ = sfm_run
    sim = broken_alignments()[broken]
    views = {k: (moved(e, sim), t) for k, (_, _, e, t) in _errors(cap, work, "views").items()}
    c, r = np.array([camera_difference(e, t) for e, t in views.values()]).T
    c *= 1000
    (_, _, e, t), = _errors(cap, work, "targets").values()
    dt, at = camera_difference(moved(e, sim), t)
    print(broken, c.mean(), c.max(), r.mean(), r.max(), dt * 1000, at)
    assert not (c.mean() < 3.0 and c.max() < 6.0 and r.mean() < 0.35 and r.max() < 0.8)
    assert not (dt * 1000 < 2.5 and at < 0.3)


def test_report_points_and_colmap_model(sfm_run):
    import pycolmap

    cap, work, rc, err = sfm_run
    assert rc == 0, err
    d = work / "sfm"
    report = json.loads((d / "report.json").read_text())
    n = SMALL_FULL["n_views"] + 2
    assert report["registered"] == f"{n}/{n}" and report["grade"] == "green"
    grades = {c["name"]: c["grade"] for c in report["checks"]}
    assert grades["views registered"] == grades["targets registered"] == grades["probes registered"] == "green"
    assert "board residual" in grades and "probe t0 pose" in grades
    assert report["alignment"]["corner_rms_mm"] < 1.5 and report["alignment"]["plane_rms_mm"] < 1.5
    assert report["camera_of"] == {"targets": "views", "probes": "views"}  # one body, one size: shared intrinsics
    rec = pycolmap.Reconstruction(str(d / "sparse" / "0"))
    assert rec.num_reg_images() == n and len(rec.cameras) == 1
    for img in rec.images.values():  # a complete COLMAP project: every image it names is in images/
        assert (d / "images" / img.name).is_file()
    pts = np.load(d / "points.npz")
    assert pts["xyz"].shape == (rec.num_points3D(), 3) and pts["rgb"].dtype == np.uint8
    assert pts["error"].shape == pts["track"].shape == (len(pts["xyz"]),) and pts["track"].min() >= 2
    # metres, board in z = 0: most points lie on the board (the object is uniform and gets few)
    assert np.median(np.abs(pts["xyz"][:, 2])) < 0.002
    stage = json.loads((d / "stage.json").read_text())
    assert "images registered" in stage["summary"] and "grade green" in stage["summary"]


def test_wrong_board_is_one_line(sfm_run, tmp_path, capsys):
    """A [board] that does not match the print: the board is found in none of the views."""
    from objcam.pipeline.cli import main

    cap, work, rc, err = sfm_run
    bad = tmp_path / "cap"
    shutil.copytree(cap, bad, ignore=shutil.ignore_patterns("truth", "objcam"))
    toml = bad / "capture.toml"
    toml.write_text(toml.read_text().replace('dictionary = "DICT_4X4_100"', 'dictionary = "DICT_5X5_100"'))
    assert main(["sfm", str(bad), "--work", str(tmp_path / "w"), "-q"]) == 2
    msg = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("objcam: error:")]
    assert len(msg) == 1 and "board was found in 0 of the" in msg[0] and "fix:" in msg[0], msg
    assert msg[0].startswith(f"objcam: error: {bad / 'views'}: ")  # names the capture's photo folder
    assert not (tmp_path / "w" / "sfm").exists()


def test_plane_height_frame_without_board():
    """The [scale] world frame on a synthetic point cloud: a plane of points, an object of known height, cameras
    on a ring looking at it, all in an arbitrary similarity frame."""
    from scipy.spatial.transform import Rotation

    from objcam.camera import look_at
    from objcam.sfm.align import Similarity, plane_height_frame

    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(-0.2, 0.2, (600, 2)), rng.normal(0, 1e-4, 600)]
    obj = np.c_[rng.normal(0, 0.02, (200, 2)), rng.uniform(0, 0.1, 200)]
    obj[0, 2] = 0.1  # the top
    eyes = [0.5 * np.array([np.cos(a) * np.cos(0.6), np.sin(a) * np.cos(0.6), np.sin(0.6)]) + [0, 0, 0.02]
            for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    poses = [look_at(e, np.array([0.0, 0.0, 0.02])) for e in eyes]
    true = Similarity(3.7, Rotation.from_rotvec([0.4, -1.0, 0.3]).as_matrix(), np.array([1.0, -2.0, 0.5]))
    to_sfm = true.inverse()
    pts = to_sfm.apply(np.r_[plane, obj])
    centres = to_sfm.apply(np.array([p[:3, 3] for p in poses]))
    axes = np.array([p[:3, 2] for p in poses]) @ to_sfm.R.T
    sim, diag = plane_height_frame(pts, centres, axes, object_height=0.1)
    back = sim.apply(pts)
    # height from the 98th percentile of the object's points: scale within 2%; plane z = 0; origin on the axis
    assert diag["scale_m_per_unit"] * true.scale ** -1 == pytest.approx(1.0, abs=0.03)
    # a test of the test (tests/broken.py): the object's height misread by 5% (0.105 m) misses the scale bound
    _, bad = plane_height_frame(pts, centres, axes, object_height=0.105)
    assert not bad["scale_m_per_unit"] * true.scale ** -1 == pytest.approx(1.0, abs=0.03), bad
    assert np.abs(back[:600, 2]).max() < 0.002
    assert np.linalg.norm(sim.apply(to_sfm.apply(np.zeros((1, 3))))[0, :2]) < 0.003
    c0 = sim.apply(centres[:1])[0]
    assert abs(c0[1]) < 1e-9 and c0[0] > 0 and c0[2] > 0  # +x towards the first view, z up
    # an untextured object has no height to measure (the uniform bunny of the default --full capture: 5 points)
    with pytest.raises(ValueError, match="sparse points on the object"):
        plane_height_frame(to_sfm.apply(np.r_[plane, obj[:5]]), centres, axes, object_height=0.1)


def test_shared_intrinsics_only_for_one_body_and_zoom(tmp_path):
    """``sfm.intrinsics=auto``: targets share the views' COLMAP camera only when size, EXIF camera and focal
    length all agree (a zoomed target keeps its own intrinsics)."""
    import cv2

    from objcam.stages.sfm import Params, _camera_of

    ingest = tmp_path / "ingest"
    (ingest / "targets" / "t0").mkdir(parents=True)
    view = ingest / "v.png"
    cv2.imwrite(str(view), np.zeros((30, 40, 3), np.uint8))
    extra = {"targets/t0": ingest / "t.png"}
    recs = [{"camera": "X body", "focal_length_mm": 35.0}]

    def target(size, focal, body="X body"):
        cv2.imwrite(str(extra["targets/t0"]), np.zeros((size[1], size[0], 3), np.uint8))
        (ingest / "targets" / "t0" / "merge.json").write_text(json.dumps({"camera": body, "focal_length_mm": focal}))
        return _camera_of(Params(), ingest, [view], extra, recs)

    assert target((40, 30), 35.0) == {"targets": "views", "probes": "views"}
    assert target((40, 30), None) == {"targets": "views", "probes": "views"}  # unknown zoom: not a difference
    assert target((40, 30), 70.0) == {}
    assert target((40, 30), 35.0, "Y body") == {}
    assert target((80, 60), 35.0) == {}
    assert _camera_of(Params(intrinsics="separate"), ingest, [view], extra, recs) == {}
