"""data_layout.md's scene checks that had no test (issue 28): a mesh with no triangles, one that does not rest on
z = 0 (and one inside the tolerance, which passes), a target with no usable pixel, and negative pixels with
neither a noise_sigma nor enough usable pixels to estimate one. Each a one-line error naming the file, through
the real CLI; the capture is never written."""

from __future__ import annotations

import numpy as np
import pytest

from objcam.image_io import write_exr
from tests.test_bad_input import TOML, assert_one_line_error, make_capture, run_scene, tree_digest, write_sphere_ply


def _ply(path, vertices, faces) -> None:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
             "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{c:g}" for c in v) for v in vertices]
    lines += [f"{len(f)} " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def test_mesh_with_no_triangles_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    _ply(cap / "object.ply", [(0, 0, 0), (0.01, 0, 0), (0, 0.01, 0.02)], [])
    before = tree_digest(cap)
    assert_one_line_error(*run_scene(cap, capsys), "object.ply", "no triangles")
    assert tree_digest(cap) == before


@pytest.mark.parametrize("lift", [0.02, -0.02])  # floating 2 cm above the plane, or sunk 2 cm into it
def test_mesh_not_resting_on_the_plane_is_refused(tmp_path, capsys, lift):
    cap = make_capture(tmp_path / "cap")
    write_sphere_ply(cap / "object.ply")  # 3 cm radius, lowest point on z = 0
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(cap / "object.ply"))
    v = ms.current_mesh().vertex_matrix() + [0, 0, lift]
    f = ms.current_mesh().face_matrix()
    ms.clear()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f))
    ms.save_current_mesh(str(cap / "object.ply"))
    assert_one_line_error(*run_scene(cap, capsys), "object.ply", "not on the support plane z = 0", "rests on z = 0")


def test_mesh_within_the_tolerance_of_the_plane_passes(tmp_path, capsys):
    """The lowest vertex within 5 mm (or 2% of the object's size) of z = 0 rests on it: 1 mm up passes."""
    cap = make_capture(tmp_path / "cap")
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(cap / "object.ply"))
    v = ms.current_mesh().vertex_matrix() + [0, 0, 0.001]
    f = ms.current_mesh().face_matrix()
    ms.clear()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f))
    ms.save_current_mesh(str(cap / "object.ply"))
    code, err = run_scene(cap, capsys)
    assert code == 0, err


def test_no_usable_pixel_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML + 'mask = "targets/t0_mask.png"\n')
    import cv2

    cv2.imwrite(str(cap / "targets" / "t0_mask.png"), np.zeros((12, 16), np.uint8))
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "no usable pixel")


def test_saturation_over_every_pixel_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML + "saturation = 0.4\n")  # the image is 0.5 everywhere
    assert_one_line_error(*run_scene(cap, capsys), "t0.exr", "no usable pixel")


def test_a_negative_pixel_without_any_noise_level_is_refused(tmp_path, capsys):
    """16 x 12 = 192 pixels, but a mask leaves 48 (< 64): no noise estimate and no noise_sigma, so even one small
    negative value is refused (it cannot be told from a wrong black level)."""
    cap = make_capture(tmp_path / "cap")
    (cap / "capture.toml").write_text(TOML + 'mask = "targets/t0_mask.png"\n')
    import cv2

    mask = np.zeros((12, 16), np.uint8)
    mask[:4] = 255
    cv2.imwrite(str(cap / "targets" / "t0_mask.png"), mask)
    img = np.full((12, 16, 3), 0.5, np.float32)
    img[1, 1, 0] = -1e-4
    write_exr(cap / "targets" / "t0.exr", img)
    code, err = run_scene(cap, capsys)
    assert_one_line_error(code, err, "t0.exr")
    assert "negative" in err, err
    img[1, 1, 0] = 1e-4  # the same image without it passes
    write_exr(cap / "targets" / "t0.exr", img)
    assert run_scene(cap, capsys)[0] == 0
