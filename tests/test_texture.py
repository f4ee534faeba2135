"""objcam.geometry's UV/bake modules and the texture stage, on the capture tests/test_geometry.py renders."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.image_io import read_exr
from objcam.pipeline.stage import StageInputs
from objcam.scene import MeshData
from tests.test_geometry import geometry_run, photo_capture  # noqa: F401  (shared session fixtures)


@pytest.fixture(scope="session")
def texture_run(photo_capture, geometry_run, tmp_path_factory):  # noqa: F811
    from objcam.stages import texture

    out = tmp_path_factory.mktemp("session_texture_out")
    res = texture.run(StageInputs(capture=photo_capture.capture, out=out, quiet=True,
                                  upstream={"ingest": photo_capture.ingest, "sfm": photo_capture.sfm,
                                            "geometry": geometry_run[0]}), texture.Params())
    return out, res.metrics


def test_support_albedo_against_board(texture_run, photo_capture):  # noqa: F811
    from objcam.synth.geometry_inputs import albedo_error

    out, m = texture_run
    err = albedo_error(out, photo_capture.truth)
    # the print's albedo (paper 0.8, ink 0.05) recovered from 12 noisy views: measured median 0.049 over the
    # board, 0.061 on plain paper (cast shadows stay baked in and pull the paper down near the object)
    assert err.support_median < 0.065 and err.paper_median < 0.08, err
    # the board is mostly paper, so a median alone passes a flat paper-white albedo (0.0 / 0.0): the 90th
    # percentile must see the ink too (measured 0.24; flat paper 0.75, the albedo's mean 0.46, turned 90 degrees
    # 0.75: test_a_broken_support_albedo_fails_the_bounds)
    assert err.support_p90 < SUPPORT_P90_MAX, err
    # the object's albedo assumes the open plane's irradiance, too much for its flanks: measured -0.24 (0.36 for
    # 0.6). This is an honest first rho for the joint solve, not an albedo measurement.
    assert -0.3 < err.object_bias < 0.0, err


SUPPORT_P90_MAX = 0.4


@pytest.mark.parametrize("broken", ["flat paper white", "flat mean", "turned 90 degrees"])
def test_a_broken_support_albedo_fails_the_bounds(texture_run, photo_capture, tmp_path, broken):  # noqa: F811
    """A test of the test: the texture stage's support albedo replaced by a broken one misses the bounds above.
    (Mirrored rows or columns are NOT caught: the board's 13 x 9 squares map onto squares of their own colour, and
    only the markers differ; measured median 0.047, p90 0.22 for the rows reversed.)"""
    import shutil

    from objcam.image_io import read_exr, write_exr
    from objcam.synth.geometry_inputs import albedo_error

    out, _ = texture_run
    for name in ("texture.json", "confidence_support.exr", "albedo_object.exr", "confidence_object.exr"):
        shutil.copy(out / name, tmp_path / name)
    est = read_exr(out / "albedo_support.exr")
    alt = {"flat paper white": lambda: np.full_like(est, 0.8),
           "flat mean": lambda: np.broadcast_to(est.mean(axis=(0, 1)), est.shape).copy(),
           "turned 90 degrees": lambda: np.rot90(est).copy()}[broken]()
    write_exr(tmp_path / "albedo_support.exr", alt)
    err = albedo_error(tmp_path, photo_capture.truth)
    assert not (err.support_median < 0.065 and err.paper_median < 0.08 and err.support_p90 < SUPPORT_P90_MAX), err


def test_contract_files(texture_run, geometry_run):  # noqa: F811
    out, m = texture_run
    obj = MeshData.load_npz(out / "object.npz")
    sup = MeshData.load_npz(out / "support.npz")
    assert obj.uv is not None and obj.uv.shape == (len(obj.vertices), 2)
    assert obj.uv.min() >= 0 and obj.uv.max() <= 1
    assert sup.uv is not None and np.all(sup.vertices[:, 2] == 0)
    geo = MeshData.load_npz(geometry_run[0] / "object.npz")
    assert len(obj.faces) == len(geo.faces)  # the same surface, split along the atlas seams
    for which in ("object", "support"):
        a = read_exr(out / f"albedo_{which}.exr")
        c = read_exr(out / f"confidence_{which}.exr")
        n = read_exr(out / f"counts_{which}.exr")
        assert a.shape[2] == 3 and a.min() >= 0 and a.max() <= 1
        assert c.shape[:2] == a.shape[:2] == n.shape[:2]
        assert c.min() >= 0 and c.max() <= 1 and n.min() >= 0 and n.max() <= 12
    data = json.loads((out / "texture.json").read_text())
    assert data["normalisation"]["reference"] == "board paper texels"


def test_occluded_support_is_unseen(texture_run):
    out, m = texture_run
    counts = read_exr(out / "counts_support.exr")[..., 0]
    conf = read_exr(out / "confidence_support.exr")[..., 0]
    n = counts.shape[0]
    c = n // 2
    # under the bunny (the origin is inside its footprint) no view sees the paper: no sample, no confidence
    assert counts[c - 2:c + 2, c - 2:c + 2].max() == 0 and conf[c - 2:c + 2, c - 2:c + 2].max() == 0
    assert m["rejected_samples"]["occluded"] > 0
    # paper in the open, 15 cm from the object, is seen by several views
    assert np.median(counts[c - 5:c + 5, 10:20]) >= 3


def test_rasterize_square():
    from objcam.geometry.uv import rasterize, surface_points

    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32) * 0.1
    f = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    face, bary = rasterize(MeshData(v, f, uv), (8, 8))
    assert (face >= 0).all()
    pts, nrm = surface_points(MeshData(v, f, uv), face, bary)
    # texel (r, c) centre is uv ((c + 0.5) / 8, (r + 0.5) / 8): here u -> x, v -> y
    rr, cc = np.nonzero(face >= 0)
    np.testing.assert_allclose(pts[:, 0], (cc + 0.5) / 8 * 0.1, atol=1e-9)
    np.testing.assert_allclose(pts[:, 1], (rr + 0.5) / 8 * 0.1, atol=1e-9)
    np.testing.assert_allclose(nrm, np.tile([0, 0, 1.0], (64, 1)))
