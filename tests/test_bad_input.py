"""Bad input: each a clear one-line error naming the file (through the real CLI, exit status 2, no traceback),
and the capture folder is never written."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from objcam.camera import Camera, look_at
from objcam.image_io import write_exr
from objcam.pipeline.cli import main

TOML = """
[scene]
object = "object.ply"

[albedo]
object = 0.5
support = [0.6, 0.6, 0.6]

[[targets]]
name = "t0"
image = "targets/t0.exr"
camera = "targets/t0.json"
"""


def write_sphere_ply(path: Path, radius: float = 0.03) -> None:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.create_sphere(radius=radius, subdiv=2)
    m = ms.current_mesh()
    v, f = m.vertex_matrix() + [0, 0, radius], m.face_matrix()
    ms.clear()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f))
    ms.save_current_mesh(str(path))


def make_capture(root: Path, size=(16, 12)) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "capture.toml").write_text(TOML)
    write_sphere_ply(root / "object.ply")
    w, h = size
    cam = Camera(width=w, height=h, fx=20.0, fy=20.0, cx=(w - 1) / 2, cy=(h - 1) / 2,
                 world_from_camera=look_at(np.array([0.3, 0.0, 0.25]), np.zeros(3)).tolist())
    (root / "targets").mkdir(exist_ok=True)
    cam.save(root / "targets" / "t0.json")
    write_exr(root / "targets" / "t0.exr", np.full((h, w, 3), 0.5, np.float32))
    return root


def tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and "objcam" not in p.relative_to(root).parts}


def run_scene(capture: Path, capsys) -> tuple[int, str]:
    code = main(["scene", str(capture), "--quiet"])
    err = capsys.readouterr().err.strip()
    return code, err


def assert_one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2, err
    assert len(err.splitlines()) == 1, f"expected one line, got:\n{err}"
    assert "Traceback" not in err
    for n in needles:
        assert n in err, f"{n!r} not in {err!r}"


def test_good_capture_passes_and_is_not_modified(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    before = tree_digest(cap)
    code, err = run_scene(cap, capsys)
    assert code == 0, err
    assert tree_digest(cap) == before
    targets = json.loads((cap / "objcam" / "scene" / "targets.json").read_text())
    assert targets[0]["n_valid"] == 16 * 12


def test_missing_capture_toml(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").unlink()
    assert_one_line_error(*run_scene(cap, capsys), "capture.toml", "not found")


def test_missing_capture_folder(tmp_path, capsys):
    assert_one_line_error(*run_scene(tmp_path / "nope", capsys), "nope", "not found")


@pytest.mark.parametrize("text,needle", [
    ("[scene\nobject=", "not valid TOML"),
    ("[scene]\nobject = 'object.ply'\n", "targets"),
    (TOML.replace("object = 0.5", "object = 1.5"), "albedo"),
    (TOML + "\n[extra]\nx = 1\n", "extra"),
])
def test_malformed_capture_toml(tmp_path, capsys, text, needle):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(text)
    assert_one_line_error(*run_scene(cap, capsys), "capture.toml", needle)


def test_mesh_that_does_not_load(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "object.ply").write_text("ply\nthis is not a mesh\n")
    assert_one_line_error(*run_scene(cap, capsys), "object.ply", "mesh")


def test_mesh_in_millimetres(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    write_sphere_ply(cap / "object.ply", radius=30.0)
    assert_one_line_error(*run_scene(cap, capsys), "object.ply", "millimetres")


def test_image_size_does_not_match_camera(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    write_exr(cap / "targets" / "t0.exr", np.full((10, 10, 3), 0.5, np.float32))
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "10x10", "16x12")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_inf_pixels(tmp_path, capsys, bad):
    cap = make_capture(tmp_path / "cap")
    img = np.full((12, 16, 3), 0.5, np.float32)
    img[3, 4, 1] = bad
    write_exr(cap / "targets" / "t0.exr", img)
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "NaN or infinite")


def test_camera_file_malformed(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "targets" / "t0.json").write_text('{"width": 16}')
    assert_one_line_error(*run_scene(cap, capsys), "t0.json", "invalid camera")


def test_image_not_an_image(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "targets" / "t0.exr").write_bytes(b"not an exr at all")
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "is named .exr but", "not an image")


def test_saturated_pixels_are_flagged_not_fitted(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    img = np.full((12, 16, 3), 0.5, np.float32)
    img[:2] = 4.0
    write_exr(cap / "targets" / "t0.exr", img)
    (cap / "capture.toml").write_text(TOML + "saturation = 4.0\n")
    code, err = run_scene(cap, capsys)
    assert code == 0, err
    targets = json.loads((cap / "objcam" / "scene" / "targets.json").read_text())
    assert targets[0]["n_valid"] == 16 * 10
