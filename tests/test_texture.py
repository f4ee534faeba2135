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

    out = tmp_path_factory.mktemp("texture_out")
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
    # the object's albedo assumes the open plane's irradiance, too much for its flanks: measured -0.24 (0.36 for
    # 0.6). This is an honest first rho for the joint solve, not an albedo measurement.
    assert -0.3 < err.object_bias < 0.0, err


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
