"""objcam.sfm.tripod: target photos from one tripod position share one camera (test_full_run_two.py end to end)."""

from __future__ import annotations

import numpy as np
import pytest

from objcam.camera import Camera, look_at
from objcam.sfm.tripod import (mean_camera, merge_same_position, nearest_separate, plane_displacement_px,
                               same_position_groups)

EYE = np.array([0.0, -0.35, 0.30])  # a tripod 46 cm from the object, 40 deg up


def _cam(eye=EYE, target=(0.0, 0.0, 0.02), fx=400.0, width=320, height=240) -> Camera:
    m = look_at(np.asarray(eye, float), np.asarray(target, float))
    return Camera(width=width, height=height, fx=fx, fy=fx, cx=width / 2 - 0.5, cy=height / 2 - 0.5,
                  world_from_camera=m.tolist())


def _rot(angle_deg: float, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
    a = np.radians(angle_deg)
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def _turned(cam: Camera, angle_deg: float, shift=(0.0, 0.0, 0.0)) -> Camera:
    m = cam.matrix.copy()
    m[:3, :3] = m[:3, :3] @ _rot(angle_deg, (1.0, 0.3, 0.2))
    m[:3, 3] += np.asarray(shift, float)
    return cam.model_copy(update={"world_from_camera": m.tolist()})


def test_displacement_is_zero_for_one_pose_and_grows_with_the_move():
    a = _cam()
    assert plane_displacement_px(a, a) == pytest.approx(0.0, abs=1e-9)
    # a 0.06 deg turn at fx = 400: about 0.4 px at the centre
    small = plane_displacement_px(a, _turned(a, 0.06))
    assert 0.2 < small < 1.0, small
    # a tripod moved by 1 cm: tens of pixels
    assert plane_displacement_px(a, _cam(eye=EYE + [0.01, 0.0, 0.0])) > 5.0


def test_a_camera_that_does_not_see_the_plane_is_never_one_position():
    up = _cam(eye=(0.0, -0.35, 0.3), target=(0.0, 0.5, 1.0))  # looking up at the sky
    assert plane_displacement_px(_cam(), up) == float("inf")


def test_shots_from_one_tripod_are_merged_and_others_kept():
    a = _cam()
    cams = {"rot0": a, "rot150": _turned(a, 0.06, (0.0003, 0.0, 0.0)),
            "moved": _cam(eye=EYE + [0.02, 0.0, 0.0]),        # another tripod position
            "zoomed": _cam(fx=440.0)}                           # same pose, other intrinsics
    groups = same_position_groups(cams, 1.0)
    assert sorted(map(sorted, groups)) == [["moved"], ["rot0", "rot150"], ["zoomed"]]
    merged, records = merge_same_position(cams, 1.0)
    assert merged["rot0"] == merged["rot150"]  # one camera: the transport builds one A for both
    assert merged["moved"] == cams["moved"] and merged["zoomed"] == cams["zoomed"]
    assert [r["targets"] for r in records] == [["rot0", "rot150"]]
    assert 0.2 < records[0]["displacement_px"] < 1.0
    # the shared pose lies between the two: half the displacement from each
    d0 = plane_displacement_px(merged["rot0"], cams["rot0"])
    d1 = plane_displacement_px(merged["rot0"], cams["rot150"])
    assert d0 == pytest.approx(d1, rel=0.1) and d0 < records[0]["displacement_px"] * 0.6
    # 0: every target keeps its own pose
    kept, none = merge_same_position(cams, 0.0)
    assert kept == cams and none == []
    # what was kept apart and nearest: the merged pair when nothing was merged, else the moved tripod (the zoomed
    # camera has other intrinsics: never compared)
    assert nearest_separate(cams, kept)["targets"] == ["rot0", "rot150"]
    apart = nearest_separate(cams, merged)
    assert apart["targets"][0] == "moved" and apart["displacement_px"] > 5.0
    assert nearest_separate({"a": a}, {"a": a}) is None


def test_mean_camera_is_rigid_and_keeps_the_intrinsics():
    a = _cam()
    cams = [_turned(a, t, (0.0002 * t, 0.0, 0.0)) for t in (-0.1, 0.0, 0.1)]
    m = mean_camera(cams)
    r = m.matrix[:3, :3]
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-12) and np.linalg.det(r) == pytest.approx(1.0)
    assert np.allclose(m.matrix, a.matrix, atol=1e-6)  # symmetric turns average out
    assert (m.fx, m.fy, m.cx, m.cy, m.width, m.height) == (a.fx, a.fy, a.cx, a.cy, a.width, a.height)
