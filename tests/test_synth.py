"""objcam.synth: a tiny synthetic capture is valid and its truth, noise model and lighting are right."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.envmap import read_latlong, rotate_z
from objcam.image_io import read_exr, write_exr
from objcam.schemas.capture import CaptureManifest, TextureAlbedo
from objcam.scene import load_mesh
from objcam.synth.assets import bundled_envmaps, load_bundled_envmap
from objcam.synth.capture import CameraSpec, SynthParams, synthesize
from objcam.synth.noise import apply_noise

TINY = CameraSpec(width=48, height=48, distance=0.4)


def test_bundled_assets():
    names = bundled_envmaps()
    assert {"forest", "courtyard", "sunset", "city", "sunrise"} <= set(names)
    env = load_bundled_envmap("forest")
    assert env.shape == (128, 256, 3) and env.dtype == np.float32 and env.min() >= 0
    # sky brighter than ground: rows are not upside down
    assert env[:64].mean() > 2 * env[64:].mean()


def test_tiny_capture(tmp_path):
    out = tmp_path / "cap"
    params = SynthParams(cameras=[TINY], rotations_deg=[0.0, 30.0], spp=8, support_albedo="dots",
                         texture_size=64, white_level=None)
    summary = synthesize(out, params)
    assert set(summary["targets"]) == {"cam0_rot0", "cam0_rot30"}
    manifest = CaptureManifest.load(out)
    assert [t.name for t in manifest.targets] == ["cam0_rot0", "cam0_rot30"]
    assert isinstance(manifest.albedo.support, TextureAlbedo) and manifest.albedo.support.extent == 1.0
    assert manifest.albedo.object == 0.6
    for t in manifest.targets:
        img = read_exr(out / t.image)
        assert img.shape == (48, 48, 3) and np.all(np.isfinite(img))
        assert t.saturation is None and t.noise_sigma is not None and t.noise_sigma > 0

    # the object: metres, centred in x and y, resting exactly on z = 0, 8 cm tall
    mesh = load_mesh(out / "object.ply")
    lo, hi = mesh.bbox
    assert lo[2] == 0.0 and hi[2] == pytest.approx(0.08, rel=1e-5)
    assert np.allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-6)

    # truth: one envmap per target (they differ), equal to the rotated bundled map
    truth = json.loads((out / "truth" / "truth.json").read_text())
    src = load_bundled_envmap("forest")
    for name, rot in (("cam0_rot0", 0.0), ("cam0_rot30", 30.0)):
        rel = truth["envmaps"][name]
        assert rel == f"truth/{name}/envmap.exr"
        assert np.allclose(read_latlong(out / rel), rotate_z(src.astype(np.float64), rot), rtol=1e-5, atol=1e-6)
        assert (out / truth["targets"][name]["clean_image"]).is_file()
    tex = read_exr(out / truth["albedo"]["support"]["texture"])
    assert tex.shape == (64, 64, 3) and np.array_equal(tex, read_exr(out / "albedo_support.exr"))


def test_unknown_albedo_and_clipping(tmp_path):
    out = tmp_path / "cap"
    params = SynthParams(cameras=[TINY], spp=4, object="sphere", support_albedo=[0.4, 0.5, 0.6],
                         support_albedo_known=False, white_level=0.3, envmap="city")
    synthesize(out, params)
    manifest = CaptureManifest.load(out)
    assert manifest.albedo.support is None and manifest.albedo.object == 0.6
    (t,) = manifest.targets
    assert t.name == "t0" and t.saturation == 0.3
    img = read_exr(out / t.image)
    clipped = (img >= 0.3).any(axis=2)
    truth = json.loads((out / "truth" / "truth.json").read_text())
    assert truth["envmaps"] == {"t0": "truth/envmap.exr"}
    assert truth["albedo"]["support"] == {"rgb": [0.4, 0.5, 0.6], "known": False}
    assert 0 < truth["targets"]["t0"]["n_clipped"] == clipped.sum() < clipped.size
    assert img.max() == np.float32(0.3)


def test_noise_model_statistics():
    """Flat field: mean = L, variance = L / exposure + (read / exposure)^2, clipping at the white level."""
    rng = np.random.default_rng(0)
    level, exposure, read = 0.5, 2000.0, 30.0
    flat = np.full((256, 256, 3), level, np.float32)
    img, clipped = apply_noise(flat, exposure, read, None, rng)
    want_var = level / exposure + (read / exposure) ** 2
    n = img.size
    assert abs(img.mean() - level) < 4 * np.sqrt(want_var / n)
    assert abs(img.var() / want_var - 1) < 4 * np.sqrt(2 / n)
    assert not clipped.any()
    # clipping: the white level caps values and flags the pixels
    img, clipped = apply_noise(flat, exposure, read, 0.5, rng)
    assert img.max() == np.float32(0.5)
    assert abs(clipped.mean() - (1 - 0.5**3)) < 0.01  # a pixel clips when any of 3 channels is >= the mean
    # no noise: only clipping
    img, clipped = apply_noise(flat, exposure, read, None, rng, noise=False)
    assert np.array_equal(img, flat)


def test_hemisphere_irradiance(tmp_path):
    """Envmap = L over the upper hemisphere, direct light only: an unshadowed plane pixel shows rho * L
    (irradiance pi L, radiance rho / pi * E). Broken variants, asserted below: off by pi, channels reversed."""
    env = np.zeros((16, 32, 3), np.float32)
    env[:8] = [1.0, 2.0, 3.0]
    write_exr(tmp_path / "hemi.exr", env)
    out = tmp_path / "cap"
    rho = np.array([0.5, 0.4, 0.3])
    cam = CameraSpec(width=32, height=32, distance=0.6, elevation_deg=60.0)
    synthesize(out, SynthParams(object="sphere", object_height=0.02, envmap=str(tmp_path / "hemi.exr"),
                                envmap_height=16, support_albedo=tuple(rho), cameras=[cam], spp=256,
                                max_depth=2, noise=False))
    img = read_exr(out / "truth" / "t0" / "clean.exr").astype(np.float64)
    assert np.array_equal(img, read_exr(out / "targets" / "t0.exr"))  # noise off
    # pixels whose ground point is over 0.15 m from the sphere: less than 0.1% of the sky hidden
    from objcam.camera import Camera

    c = Camera.load(out / "targets" / "t0.json")
    vv, uu = np.mgrid[0 : c.height, 0 : c.width].astype(float)
    o, d = c.rays(uu, vv)
    t = -o[..., 2] / d[..., 2]
    ground = o + t[..., None] * d
    far = (t > 0) & (np.linalg.norm(ground[..., :2], axis=-1) > 0.15)
    assert far.sum() > 100
    want = rho * np.array([1.0, 2.0, 3.0])
    ratio = img[far].mean(axis=0) / want
    assert np.all(np.abs(ratio - 1) < 0.02), ratio
    # a test of the test (tests/broken.py): the radiance off by pi (a lost 1 / pi) and the albedo's channels
    # reversed miss it
    for broken in (img[far].mean(axis=0) / np.pi / want, img[far].mean(axis=0)[::-1] / want):
        assert not np.all(np.abs(broken - 1) < 0.02), broken
