"""Issue 24 (hostile inputs) and issue 22 item 4 (zero-mean noise), for the capture's own files: each defect as a
run through the real CLI that must end with exit 2 and one line naming the file (or, for data that is fine, a
run that passes), and the capture folder is never written."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from objcam.camera import Camera, look_at
from objcam.image_io import read_exr, write_exr
from objcam.pipeline.cli import main
from tests.test_bad_input import TOML, assert_one_line_error, make_capture, run_scene, tree_digest

PLY_HEAD = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 2\nproperty list uchar int vertex_indices\nend_header\n")


def _camera_dict(cap: Path) -> dict:
    return json.loads((cap / "targets" / "t0.json").read_text())


def _write_camera(cap: Path, d: dict) -> None:
    (cap / "targets" / "t0.json").write_text(json.dumps(d))


@pytest.mark.parametrize("coord", ["nan", "inf", "-inf"])
def test_mesh_with_non_finite_vertex_is_refused(tmp_path, capsys, coord):
    cap = make_capture(tmp_path / "cap")
    (cap / "object.ply").write_text(PLY_HEAD + f"0 0 0\n0.01 0 0\n0 0.01 {coord}\n0 0.01 0.01\n3 0 1 2\n3 0 1 3\n")
    assert_one_line_error(*run_scene(cap, capsys), "object.ply", "not finite")


def test_obj_with_nan_vertex_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML.replace("object.ply", "object.obj"))
    (cap / "object.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 nan\nv 0 0.01 0.01\nf 1 2 3\nf 1 2 4\n")
    assert_one_line_error(*run_scene(cap, capsys), "object.obj", "not finite")


@pytest.mark.parametrize("ext", ["ply", "obj"])
def test_face_index_past_vertex_list_is_named(tmp_path, capsys, ext):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML.replace("object.ply", f"object.{ext}"))
    if ext == "ply":
        (cap / "object.ply").write_text(PLY_HEAD + "0 0 0\n0.01 0 0\n0 0.01 0\n0 0.01 0.01\n3 0 1 2\n3 0 1 9\n")
    else:
        (cap / "object.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0.01\nf 1 2 3\nf 1 2 9\n")
    code, err = run_scene(cap, capsys)
    assert_one_line_error(code, err, f"object.{ext}", "past the vertex list")
    assert "Unable to open" not in err


@pytest.mark.parametrize("field,value,needle", [
    ("fx", -160.0, "fx"), ("fx", 0.0, "fx"), ("fy", float("nan"), "fy"), ("cx", float("inf"), "cx"),
    ("width", 0, "width"),
])
def test_bad_intrinsics_are_refused(tmp_path, capsys, field, value, needle):
    cap = make_capture(tmp_path / "cap")
    d = _camera_dict(cap)
    d[field] = value
    (cap / "targets" / "t0.json").write_text(json.dumps(d).replace("NaN", "NaN"))  # json.dumps writes NaN/Infinity
    assert_one_line_error(*run_scene(cap, capsys), "t0.json", needle)


@pytest.mark.parametrize("damage", ["nan_translation", "not_orthonormal", "reflection", "huge"])
def test_bad_pose_is_refused(tmp_path, capsys, damage):
    cap = make_capture(tmp_path / "cap")
    d = _camera_dict(cap)
    m = np.asarray(d["world_from_camera"])
    if damage == "nan_translation":
        m[0, 3] = np.nan
    elif damage == "huge":  # finite, but r^T r overflows: one line, no RuntimeWarning on stderr
        m[1, 2] = 1e300
    elif damage == "not_orthonormal":
        m[:3, 0] *= 1.1
    else:
        m[:3, 0] *= -1
    d["world_from_camera"] = m.tolist()
    _write_camera(cap, d)
    with warnings.catch_warnings(record=True) as caught:  # a warning would be a second line on stderr
        warnings.simplefilter("always")
        assert_one_line_error(*run_scene(cap, capsys), "t0.json", "world_from_camera")
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in caught]


def test_unknown_camera_key_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    d = _camera_dict(cap) | {"focal": 3.0}
    _write_camera(cap, d)
    assert_one_line_error(*run_scene(cap, capsys), "t0.json", "focal")


@pytest.mark.parametrize("key", ["a\u2028b", "x\x1cy", "\x1b[31mred", "line\rbreak"])
def test_odd_characters_in_an_unknown_key_stay_on_one_line(tmp_path, capsys, key):
    cap = make_capture(tmp_path / "cap")
    _write_camera(cap, _camera_dict(cap) | {key: 1})
    code, err = run_scene(cap, capsys)
    assert_one_line_error(code, err, "t0.json", "Extra inputs")
    assert "\x1b" not in err


def test_srgb_png_target_is_refused_unless_encoding_given(tmp_path, capsys):
    import cv2

    cap = make_capture(tmp_path / "cap")
    img = np.full((12, 16, 3), 128, np.uint8)
    cv2.imwrite(str(cap / "targets" / "t0.png"), img)
    (cap / "capture.toml").write_text(TOML.replace("targets/t0.exr", "targets/t0.png"))
    assert_one_line_error(*run_scene(cap, capsys), "t0.png", "not linear", "encoding")
    (cap / "capture.toml").write_text(TOML.replace('image = "targets/t0.exr"',
                                                   'image = "targets/t0.png"\nencoding = "srgb"'))
    code, err = run_scene(cap, capsys)
    assert code == 0, err
    got = read_exr(cap / "objcam" / "scene" / "targets" / "t0" / "image.exr")
    assert got[0, 0, 0] == pytest.approx(((128 / 255 + 0.055) / 1.055) ** 2.4, rel=1e-3)  # the sRGB curve


def test_jpeg_bytes_named_exr_are_refused(tmp_path, capsys):
    import cv2

    cap = make_capture(tmp_path / "cap")
    ok, buf = cv2.imencode(".jpg", np.full((12, 16, 3), 128, np.uint8))
    (cap / "targets" / "t0.exr").write_bytes(buf.tobytes())
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "named .exr but its content is JPG")


@pytest.mark.parametrize("name", [".", ".."])
def test_dot_target_names_are_refused(tmp_path, capsys, name):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML.replace('name = "t0"', f'name = "{name}"'))
    assert_one_line_error(*run_scene(cap, capsys), "capture.toml", "name")


@pytest.mark.parametrize("line,needle", [("plane_size = inf", "plane_size"), ("plane_size = 1e-9", "plane_size"),
                                         ("plane_size = nan", "plane_size")])
def test_bad_plane_size_is_a_user_error(tmp_path, capsys, line, needle):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML.replace('object = "object.ply"', f'object = "object.ply"\n{line}'))
    code, err = run_scene(cap, capsys)
    assert_one_line_error(code, err, "capture.toml", needle)
    assert "please report" not in err


def test_boolean_albedo_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML.replace("object = 0.5", "object = true"))
    assert_one_line_error(*run_scene(cap, capsys), "capture.toml", "true/false")


def test_uniform_albedo_keyword_and_a_misspelt_one(tmp_path, capsys):
    """``object = "uniform"`` (any case) declares one unknown albedo for the surface; anything else in quotes is a
    texture file, so a misspelling is a missing file named in one line, not a silent per-pixel albedo."""
    import json

    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML.replace("object = 0.5", 'object = "Uniform"'))
    code, _ = run_scene(cap, capsys)
    assert code == 0
    desc = json.loads((cap / "objcam" / "scene" / "scene.json").read_text())
    assert desc["albedo_object"] == {"rgb": None, "texture": None, "initial": None, "uniform": True}
    (cap / "capture.toml").write_text(TOML.replace("object = 0.5", 'object = "unifrom"'))
    assert_one_line_error(*run_scene(cap, capsys), "unifrom")


def test_folder_where_a_file_is_expected(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "targets" / "t0.exr").unlink()
    (cap / "targets" / "t0.exr").mkdir()
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "is a folder")


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_inputs_outside_the_capture_are_refused_unless_allowed(tmp_path, capsys, how):
    cap = make_capture(tmp_path / "cap")
    outside = tmp_path / "elsewhere.exr"
    write_exr(outside, np.full((12, 16, 3), 0.5, np.float32))
    ref = {"dotdot": "../elsewhere.exr", "absolute": str(outside), "symlink": "targets/link.exr"}[how]
    if how == "symlink":
        (cap / "targets" / "link.exr").symlink_to(outside)
    (cap / "capture.toml").write_text(TOML.replace("targets/t0.exr", ref))
    code, err = run_scene(cap, capsys)
    assert_one_line_error(code, err, "outside the capture folder", "--allow-outside-inputs")
    assert not (cap / "objcam" / "scene").exists()
    assert main(["scene", str(cap), "--quiet", "--allow-outside-inputs"]) == 0


@pytest.mark.timeout(60)
def test_fifo_and_device_inputs_fail_fast(tmp_path, capsys):
    """A FIFO would block the content hash forever (the test's timeout is the hang detector)."""
    cap = make_capture(tmp_path / "cap")
    (cap / "targets" / "t0.exr").unlink()
    os.mkfifo(cap / "targets" / "t0.exr")
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "not a regular file")
    (cap / "targets" / "t0.exr").unlink()
    (cap / "targets" / "t0.exr").symlink_to("/dev/zero")
    code, err = main(["scene", str(cap), "--quiet", "--allow-outside-inputs"]), capsys.readouterr().err.strip()
    assert_one_line_error(code, err, "t0.exr", "not a regular file")


def test_hot_pixel_is_excluded_and_said(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap", size=(32, 24))
    img = np.full((24, 32, 3), 0.5, np.float32) + np.random.default_rng(0).normal(0, 0.01, (24, 32, 3)).astype(
        np.float32)
    img[10, 20] = 1e6
    write_exr(cap / "targets" / "t0.exr", img)
    code, err = run_scene(cap, capsys)
    assert code == 0, err
    rec = json.loads((cap / "objcam" / "scene" / "stage.json").read_text())
    assert rec["metrics"]["target_checks"]["t0"]["hot_pixels_excluded"] == 1
    assert "1 hot pixel(s) excluded" in rec["summary"]
    import cv2

    valid = cv2.imread(str(cap / "objcam" / "scene" / "targets" / "t0" / "valid.png"), cv2.IMREAD_UNCHANGED)
    assert valid[10, 20] == 0 and (valid > 0).sum() == 24 * 32 - 1


def test_camera_that_sees_no_object_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    d = _camera_dict(cap)
    d["world_from_camera"] = look_at(np.array([3.0, 0.0, 0.25]), np.array([6.0, 0.0, 0.0])).tolist()
    _write_camera(cap, d)
    assert_one_line_error(*run_scene(cap, capsys), "t0.json", "does not see the object")


def test_capture_is_never_written(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    before = tree_digest(cap)
    for toml in (TOML.replace('name = "t0"', 'name = ".."'), TOML.replace("object = 0.5", "object = true")):
        (cap / "capture.toml").write_text(toml)
        run_scene(cap, capsys)
        (cap / "capture.toml").write_text(TOML)
    assert tree_digest(cap) == before
