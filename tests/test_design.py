"""``objcam design``: the occluder comparison on a small setup (64 x 64 image, 16 x 32 envmap), run once through
the real CLI with the bunny, the sphere, the coded mask and the sphere again as a user mesh file at another scale.
The numbers must reproduce the method's findings: the sphere resolves every azimuth alike (its uncertainty is
more uniform) but is worse on average than the bunny; the mask is excellent near the zenith (its field of view)
and blind at the horizon."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from objcam.design.occluders import coded_mask, mask_pattern, normalise
from objcam.design.params import DesignParams
from objcam.design.scene import build_transport, design_camera, reference_scale
from objcam.image_io import read_exr
from objcam.pipeline.cli import main
from objcam.scene import MeshData
from objcam.synth.assets import icosphere, write_ply
from tests.test_report import check_page

SMALL = ["--image-size", "64", "--env-height", "16"]


@pytest.fixture(scope="module")
def design(tmp_path_factory) -> tuple[Path, dict, str]:
    tmp = tmp_path_factory.mktemp("design")
    v, f = icosphere(4)
    write_ply(tmp / "ball.ply", v * 37.0 + 5.0, f)  # the sphere again, in other units and off-centre
    out = tmp / "out"
    assert main(["design", str(out), "--quiet", "--mesh", str(tmp / "ball.ply"), *SMALL]) == 0
    return out, json.loads((out / "design.json").read_text()), str(tmp / "ball.ply")


def numbers(results: dict, name: str) -> dict:
    return results["objects"][name]["numbers"]


def test_sphere_is_more_uniform_but_worse_on_average_than_the_bunny(design):
    _, res, _ = design
    bunny, sphere = numbers(res, "bunny"), numbers(res, "sphere")
    # measured: bunny mean 584, sphere 1117 (radiance per unit pixel noise)
    assert sphere["uncertainty_mean"] > 1.5 * bunny["uncertainty_mean"]
    assert sphere["uncertainty_median"] > bunny["uncertainty_median"]
    assert sphere["fraction_resolved"] < bunny["fraction_resolved"]
    # more uniform: worst / mean 6.28 against 6.90, and half the variation across azimuth (0.068 against 0.138)
    assert sphere["spread"] < 0.95 * bunny["spread"]
    assert sphere["azimuth_cv"] < 0.6 * bunny["azimuth_cv"]


def test_mask_is_excellent_near_the_zenith_and_blind_at_the_horizon(design):
    _, res, _ = design
    mask, bunny, sphere = numbers(res, "mask"), numbers(res, "bunny"), numbers(res, "sphere")
    bound = res["setup"]["uncertainty_bound"]
    # measured: zenith band 459, horizon band 4112 (bound 7249)
    assert mask["uncertainty_zenith"] < mask["uncertainty_horizon"] / 5
    assert mask["uncertainty_zenith"] < bunny["uncertainty_zenith"] / 2
    assert mask["uncertainty_zenith"] < sphere["uncertainty_zenith"] / 4
    assert mask["uncertainty_horizon"] > 5 * max(bunny["uncertainty_horizon"], sphere["uncertainty_horizon"])
    # the lowest row above the horizon casts the same unshadowed cosine on every visible pixel whatever its
    # azimuth: its 32 columns coincide, so at best their sum is learnt and each texel's uncertainty lies between
    # sqrt(31/32) of the ridge bound (sum known exactly) and the bound (nothing known), the same in every azimuth
    u = read_exr(design[0] / "mask" / "uncertainty.exr")[..., 0]
    h = u.shape[0]
    assert u.shape == (16, 32)
    row = u[h // 2 - 1].astype(np.float64)
    assert np.ptp(row) < 1e-5 * row.mean()
    assert bound * np.sqrt(31 / 32) * (1 - 1e-6) <= row.min() and row.max() <= bound * (1 + 1e-6)
    assert np.all(u[h // 2:] == 0)  # below the horizon: not scored
    upper = u[: h // 2]
    assert upper.mean() == pytest.approx(mask["uncertainty_mean"], rel=1e-5)
    assert upper.max() == pytest.approx(mask["uncertainty_worst"], rel=1e-5)


def test_user_mesh_is_scaled_like_the_builtin(design):
    """A mesh file is normalised to the same size and placement: the sphere given as a file in other units
    scores like the built-in sphere (same transport up to float32 rounding of the vertices)."""
    _, res, path = design
    ball, sphere = res["objects"]["ball"], res["objects"]["sphere"]
    assert ball["kind"] == "mesh" and ball["source"] == path
    for key in ("uncertainty_mean", "uncertainty_worst", "uncertainty_zenith", "uncertainty_horizon",
                "leverage_sum"):
        assert ball["numbers"][key] == pytest.approx(sphere["numbers"][key], rel=2e-3), key
    assert ball["numbers"]["effective_rank"] == pytest.approx(sphere["numbers"]["effective_rank"], abs=2)


def test_outputs_are_complete_and_consistent(design):
    out, res, _ = design
    assert list(res["objects"]) == ["bunny", "sphere", "mask", "ball"]
    for name, r in res["objects"].items():
        n = r["numbers"]
        assert n["pixels"] == 64 * 64  # an overhead camera sees only surfaces
        assert 0 < n["effective_rank"] <= n["texels"] <= 16 * 32
        lev = read_exr(out / name / "leverage.exr")[..., 0]
        assert lev.shape == (64, 64)
        assert lev.sum() == pytest.approx(n["leverage_sum"], rel=1e-4)
        assert 0 <= lev.min() and lev.max() < 1
        for f in ("uncertainty.png", "leverage.png"):
            assert (out / name / f).read_bytes()[:4] == b"\x89PNG"
        assert n["uncertainty_worst"] <= res["setup"]["uncertainty_bound"] * (1 + 1e-9)
    assert (out / "comparison.png").read_bytes()[:4] == b"\x89PNG"
    c, text = check_page(out / "index.html")
    assert c.images == 1
    for name in res["objects"]:
        assert name in text
        assert f"{numbers(res, name)['uncertainty_mean']:.4g}" in text


def test_terminal_table(design, capsys):
    out, res, _ = design
    from rich.console import Console

    from objcam.design.cli import print_table

    print_table(Console(width=80, force_terminal=False), res)
    text = capsys.readouterr().out
    assert max(len(line) for line in text.splitlines()) <= 80
    row = next(line for line in text.splitlines() if line.strip().startswith("mask"))
    assert f"{numbers(res, 'mask')['uncertainty_zenith']:.0f}" in row


def test_reference_scale_is_the_unoccluded_plane():
    """s_ref (the unit of the ridge weight) equals the mean squared upper-texel column norm of A for the plane
    with an occluder far outside the view."""
    p = DesignParams(image_size=24, env_height=8, subpixel_samples=4, samples=1)
    cam = design_camera(p)
    far = MeshData(np.array([[50, 50, 0], [50.01, 50, 0], [50, 50.01, 0.01]], np.float32),
                   np.array([[0, 1, 2]], np.uint32))
    tr, _ = build_transport(far, p, cam)
    upper = tr.directions[:, 2] > 0
    norms = np.einsum("mn,mn->n", tr.A[0][:, upper], tr.A[0][:, upper], dtype=np.float64)
    assert np.sum(upper) == 8 * 16 // 2
    assert norms.mean() == pytest.approx(reference_scale(p, cam), rel=1e-3)


def test_mask_geometry():
    holes = mask_pattern(16, 0.5, 0)
    assert holes.sum() == 128
    m = coded_mask(0.2, 0.15, 16, 0.5, 0)
    assert len(m.faces) == 2 * (256 - 128)
    np.testing.assert_allclose(m.vertices[:, 2], 0.15)
    np.testing.assert_allclose(m.vertices[:, :2].min(axis=0), [-0.1, -0.1], atol=0.0125 + 1e-7)
    # each opaque cell is two triangles of total area c^2
    v = m.vertices.astype(np.float64)[m.faces.astype(np.int64)]
    area = 0.5 * np.abs(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])[:, 2]).sum()
    assert area == pytest.approx(128 * (0.2 / 16) ** 2, rel=1e-5)
    v = normalise(np.array([[0, 0, 3.0], [10, 4, 5], [2, 2, 4]]), 0.2)
    np.testing.assert_allclose(v.max(axis=0) - v.min(axis=0), [0.2, 0.08, 0.04], rtol=1e-6)
    assert v[:, 2].min() == 0 and v[:, 0].min() == pytest.approx(-0.1)


def test_bad_input_is_one_line(tmp_path, capsys):
    cwd = Path.cwd()
    assert main(["design", str(tmp_path / "o"), "--mesh", str(tmp_path / "nope.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nope.ply" in err and "--mesh" in err
    assert main(["design", str(tmp_path / "o"), "--objects", "teapot"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "teapot" in err
    (tmp_path / "bad.ply").write_text("not a mesh")
    assert main(["design", str(tmp_path / "o"), "--mesh", str(tmp_path / "bad.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.ply" in err and "--mesh" in err
    # pymeshlab leaves a failed load in the mesh's folder; the process must come back where it was
    assert Path.cwd() == cwd
