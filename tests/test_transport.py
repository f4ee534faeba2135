"""Transport stage: direct-light A against geometry and analytic integrals, culling against brute force, direct
against Mitsuba's path tracer, storage, pooling, determinism and model=auto."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from objcam.camera import Camera, look_at
from objcam.envmap import EnvGrid
from objcam.image_io import write_exr
from objcam.pipeline.stage import StageInputs
from objcam.scene import AlbedoValue, MeshData, SceneDescription, make_plane
from objcam.stages import transport as stage
from objcam.transport import load_transport, pool_target
from objcam.transport.direct import DirectModel
from objcam.transport.geometry import SceneGeometry, primary_samples
from objcam.transport.path import PathRenderer

R = 0.1  # sphere radius, centred at (0, 0, R) on the plane z = 0
SIZE = 32
ENV_H = 8


def _write_artifact(folder: Path, obj=(0.5, 0.5, 0.5), sup=(0.8, 0.8, 0.8), cams=1, noise=None) -> Camera:
    import pymeshlab

    folder.mkdir(parents=True, exist_ok=True)
    ms = pymeshlab.MeshSet()
    ms.create_sphere(radius=R, subdiv=3)
    m = ms.current_mesh()
    v = m.vertex_matrix().astype(np.float32)
    v[:, 2] += R
    MeshData(v, m.face_matrix().astype(np.uint32)).save(folder / "object.npz")
    make_plane(2.0).save(folder / "support.npz")
    desc = SceneDescription(object_mesh="object.npz", support_mesh="support.npz", support_is_plane=True,
                            albedo_object=AlbedoValue(rgb=obj) if obj else AlbedoValue(),
                            albedo_support=AlbedoValue(rgb=sup) if sup else AlbedoValue())
    (folder / "scene.json").write_text(desc.model_dump_json())
    f = SIZE / 2 / np.tan(0.3)
    cam = Camera(width=SIZE, height=SIZE, fx=f, fy=f, cx=(SIZE - 1) / 2, cy=(SIZE - 1) / 2,
                 world_from_camera=look_at(np.array([0.7, -0.7, 0.55]), np.array([0, 0, 0.06])).tolist())
    recs = []
    for i in range(cams):
        name = f"t{i}"
        (folder / "targets" / name).mkdir(parents=True, exist_ok=True)
        write_exr(folder / "targets" / name / "image.exr", np.full((SIZE, SIZE, 3), 0.5, np.float32))
        cv2.imwrite(str(folder / "targets" / name / "valid.png"), np.full((SIZE, SIZE), 255, np.uint8))
        recs.append(dict(name=name, camera=cam.model_dump(), image=f"targets/{name}/image.exr",
                         valid=f"targets/{name}/valid.png", noise_sigma=noise, n_valid=SIZE * SIZE,
                         n_pixels=SIZE * SIZE))
    (folder / "targets.json").write_text(json.dumps(recs))
    return cam


def _run(art: Path, out: Path, **params) -> dict:
    out.mkdir(parents=True)
    res = stage.run(StageInputs(capture=art, upstream={"scene": art}, out=out),
                    stage.Params(env_height=ENV_H, **params))
    return res.metrics


@pytest.fixture(scope="module")
def art(tmp_path_factory) -> tuple[Path, Camera]:
    folder = tmp_path_factory.mktemp("scene")
    return folder, _write_artifact(folder, cams=2)


def hit_samples(art, env_height: int = ENV_H, n_sub: int = 16):
    """(SceneGeometry, PixelSamples) of the scene ``art`` (folder, camera): ``n_sub`` sub-pixel samples (seed 0) for
    the pixels that see a surface."""
    folder, cam = art
    desc = SceneDescription.model_validate_json((folder / "scene.json").read_text())
    geo = SceneGeometry.load(desc, folder, env_height=env_height)
    s = primary_samples(geo, cam, 1, n_sub, np.arange(SIZE * SIZE), SIZE, seed=0)
    return geo, s.subset(s.hit.any(axis=1))


@pytest.fixture(scope="module")
def model(art):
    """DirectModel (K=4 rays, S=16 sub-pixel samples) and its SceneGeometry for the pixels that see a surface."""
    geo, s = hit_samples(art)
    return geo, s, DirectModel(geo, s, ENV_H, 1, rays=4, seed=0, image_shape=(SIZE, SIZE))


def _plane_pixels(s, full=True):
    ok = (~s.on_object & s.hit).all(axis=1) if full else ~s.on_object.any(axis=1)
    return np.nonzero(ok)[0]


def test_unshadowed_plane_pixel_matches_cosine_integral(model):
    """A plane pixel far from the sphere: A[p, j] = rho / pi * int_texel cos = rho / pi * Delta phi *
    (sin^2 theta1 - sin^2 theta0) / 2 above the horizon (except texels towards the sphere), 0 below it."""
    geo, s, dm = model
    plane = _plane_pixels(s)
    dist = np.linalg.norm(s.pos[plane, :, :2].mean(axis=1), axis=1)
    p = plane[np.argmax(dist)]
    A = dm.columns(np.arange(EnvGrid(ENV_H).n_texels))[0, p].reshape(ENV_H, 2 * ENV_H)
    t = EnvGrid(ENV_H).theta_edges()
    band = 0.8 / np.pi * (np.pi / ENV_H) * (np.sin(t[1:]) ** 2 - np.sin(t[:-1]) ** 2) / 2  # dphi = 2 pi / W
    up = A[: ENV_H // 2]
    want = band[: ENV_H // 2, None]
    close = np.abs(up / want - 1) < 1e-3
    assert close.mean() > 0.9  # the rest look towards the sphere
    towards = EnvGrid(ENV_H).directions()[: ENV_H // 2] @ (np.array([0, 0, R]) - s.pos[p].mean(axis=0))
    assert np.all(towards[~close] > 0)
    assert np.all(up[~close] <= want[np.nonzero(~close)[0], 0] * 1.05)  # traced: K cosine samples, maybe shadow
    assert np.all(A[ENV_H // 2 :] == 0)


def _sphere_hit(o: np.ndarray, w: np.ndarray, radius: float) -> np.ndarray:
    """Rays o + t w (t > 0) meeting the sphere of ``radius`` about (0, 0, R)."""
    oc = o - np.array([0, 0, R])
    b = np.sum(oc * w, axis=-1)
    c = np.sum(oc * oc, axis=-1) - radius**2
    disc = b * b - c
    return (disc > 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 0)


def test_shadow_lies_where_the_sphere_is_and_culling_matches_brute_force(model):
    geo, s, dm = model
    grid = EnvGrid(ENV_H)
    tex = np.arange(grid.n_texels)
    A = dm.columns(tex)[0]
    # 1) geometry: for texel (2, c) and plane pixels, rays from every sample point to dense directions in the
    # texel either all miss a sphere slightly larger than the mesh (lit) or all hit one slightly smaller (umbra)
    plane = _plane_pixels(s)
    rng = np.random.default_rng(0)
    uv = rng.random((96, 2))
    checked = {"lit": 0, "umbra": 0}
    for c in range(0, 2 * ENV_H, 2):
        j = 2 * 2 * ENV_H + c
        w = grid.sample_in_texels(uv[:, 0], uv[:, 1], np.full(96, 2), np.full(96, c))
        o = s.pos[plane][:, :, None, :]
        big = _sphere_hit(o, w[None, None], R * 1.01).reshape(len(plane), -1)
        small = _sphere_hit(o, w[None, None], R * 0.98).reshape(len(plane), -1)
        unocc = (0.8 / np.pi) * dm.tab.wvec[j, 2]
        lit = ~big.any(axis=1)
        umbra = small.all(axis=1)
        assert np.allclose(A[plane[lit], j], unocc, rtol=1e-4)  # exact cosine integral when nothing blocks
        assert np.all(A[plane[umbra], j] == 0)
        checked["lit"] += lit.sum()
        checked["umbra"] += umbra.sum()
    assert checked["umbra"] > 5 and checked["lit"] > 500
    # 2) the culled fast path against tracing every ray (one per sub-pixel sample)
    zero, analytic, _ = dm.classify(tex)
    pi, ti = np.nonzero(zero)
    vis = dm.visibility(pi, tex[ti], all_samples=True)
    assert np.all(vis[:, 1] == 0)  # below every normal's horizon, or provably blocked by the support plane
    pi, ti = np.nonzero(analytic)
    vis = dm.visibility(pi, tex[ti], all_samples=True)
    assert np.array_equal(vis[:, 0], vis[:, 1]) and vis[:, 0].sum() > 0  # every ray of an analytic pair escapes
    bf = DirectModel(geo, s, ENV_H, 1, rays=4, seed=0, cull=False, image_shape=(SIZE, SIZE))
    B = bf.columns(tex)[0]
    bg = dm.bg[:, tex].toarray() if dm.bg is not None else 0
    assert np.all((B - bg)[zero] == 0)
    # the two estimators (ratio with the exact cosine integral, plain mean) agree column by column
    err = np.linalg.norm(A - B, axis=0) / np.maximum(np.linalg.norm(B, axis=0), 1e-12)
    assert np.median(err[np.linalg.norm(B, axis=0) > 0]) < 0.02
    # a test of the test (tests/broken.py): the columns one texel off (an index slip) miss it (measured: 0.019;
    # one texel off 0.19)
    off = np.linalg.norm(np.roll(A, 1, axis=1) - B, axis=0) / np.maximum(np.linalg.norm(B, axis=0), 1e-12)
    assert np.median(off[np.linalg.norm(B, axis=0) > 0]) >= 0.02
    fresh = DirectModel(geo, s, ENV_H, 1, rays=4, seed=0, image_shape=(SIZE, SIZE))
    assert np.array_equal(fresh.columns(tex)[0], A)
    assert fresh.stats.rays_traced < 0.5 * bf.stats.rays_traced


def test_direct_agrees_with_path_traced_direct_light(model):
    geo, s, dm = model
    pr = PathRenderer(geo, _camera_of(model), 1, s.pixel_index, ENV_H)
    grid = EnvGrid(ENV_H)
    for j in (1 * 2 * ENV_H + 3, 2 * 2 * ENV_H + 9, 3 * 2 * ENV_H + 14):
        a = dm.columns(np.array([j]))[0, :, 0]
        env = pr.onehot([j])
        r1 = pr.render(env, 128, 2, seed=1)[:, 0]
        r2 = pr.render(env, 128, 2, seed=2)[:, 0]
        ref = 0.5 * (r1 + r2)
        noise = np.linalg.norm(r1 - r2) / 2
        def col_err(col):
            return np.sqrt(max(np.linalg.norm(col - ref) ** 2 - noise**2, 0.0)) / np.linalg.norm(ref)

        bound = 0.02 + 2 * noise / np.linalg.norm(ref)
        assert col_err(a) < bound, (j, col_err(a), noise / np.linalg.norm(ref))
        assert grid.n_texels == 2 * ENV_H * ENV_H
        # a test of the test: the next texel's column (a texel convention off by one) and the column a factor pi
        # off (radiance against irradiance units) miss the bound
        assert col_err(dm.columns(np.array([j + 1]))[0, :, 0]) > bound, j
        assert col_err(a / np.pi) > bound and col_err(a * np.pi) > bound, j


def _camera_of(model):
    geo, s, dm = model
    return Camera.model_validate(json.loads((geo.root / "targets.json").read_text())[0]["camera"])


def test_stage_storage_dropped_pixels_texels_and_predict(art, model, tmp_path):
    folder, cam = art
    # one sample set for every pixel (object pixels at the support's counts), to compare with the fixture's model
    m = _run(folder, tmp_path / "a", model="direct", samples=4, subpixel_samples=16, object_samples=4,
             object_subpixel_samples=16)
    index = json.loads((tmp_path / "a" / "index.json").read_text())
    assert index["targets"] == {"t0": "cam0", "t1": "cam0"}  # one A for two targets sharing a camera
    T = load_transport(tmp_path / "a", "t1")
    geo, s, dm = model
    # pixels: exactly those whose sub-pixel rays hit a surface (same seed, same samples)
    s_all = primary_samples(geo, cam, 1, 16, np.arange(SIZE * SIZE), SIZE, seed=0)
    assert np.array_equal(T.pixel_index, np.nonzero(s_all.hit.any(axis=1))[0])
    assert m["pixels_kept"] == T.n_pixels < SIZE * SIZE
    # texels: exactly the nonzero columns
    full = dm.columns(np.arange(EnvGrid(ENV_H).n_texels))
    assert np.array_equal(T.texel_index, np.nonzero(np.any(full != 0, axis=(0, 1)))[0])
    assert np.array_equal(T.A, full[:, :, T.texel_index])
    assert 0 < T.n_texels < EnvGrid(ENV_H).n_texels and m["texels_kept"] == T.n_texels
    assert T.A.dtype == np.float32 and T.channels == 1
    assert np.allclose(T.albedo[T.object_fraction == 1], 0.5) and np.allclose(T.albedo[T.object_fraction == 0], 0.8)
    assert not T.unknown_albedo.any()
    # the stored Gram matrix: A^T A, read once and kept read-only (a solve asks for it several times)
    G = T.gram()
    assert G is T.gram() and not G.flags.writeable
    assert np.allclose(G[0], T.A[0].astype(np.float64).T @ T.A[0].astype(np.float64), rtol=1e-6, atol=1e-9)
    # predict scatters A x into the image
    x = np.zeros((T.n_texels, 3), np.float32)
    x[5] = (1.0, 2.0, 3.0)
    img = T.predict(x)
    assert img.shape == (SIZE, SIZE, 3)
    flat = img.reshape(-1, 3)
    assert np.allclose(flat[T.pixel_index], T.A[0][:, 5:6] * np.array([1, 2, 3], np.float32))
    others = np.setdiff1d(np.arange(SIZE * SIZE), T.pixel_index)
    assert np.all(flat[others] == 0)
    # an envmap through predict looks like the path-traced image of the same envmap
    env = np.zeros((ENV_H, 2 * ENV_H, 3), np.float32)
    env[:ENV_H // 2] = np.linspace(0.2, 1.0, 2 * ENV_H)[None, :, None]
    pr = PathRenderer(geo, cam, 1, T.pixel_index, ENV_H)
    r1, r2 = pr.render(env, 64, 2, seed=3), pr.render(env, 64, 2, seed=4)
    ref, noise2 = 0.5 * (r1 + r2), np.sum((r1 - r2) ** 2) / 4
    pred = T.predict_pixels(T.x_from_envmap(env))

    def rel_err(p: np.ndarray) -> float:  # relative error against the path-traced image, its noise subtracted
        return float(np.sqrt(max(np.sum((p - ref) ** 2) - noise2, 0)) / np.linalg.norm(ref))

    assert rel_err(pred) < 0.02
    # a test of the test (tests/broken.py): the envmap turned 180 degrees before predict, and a prediction off by
    # pi (a lost 1 / pi), miss it (measured: 0.014; turned 0.068, off by pi 0.68)
    turned = T.predict_pixels(T.x_from_envmap(np.roll(env, ENV_H, axis=1)))
    assert rel_err(turned) >= 0.02 and rel_err(pred / np.pi) >= 0.02
    assert np.array_equal(T.envmap_from_x(T.x_from_envmap(env))[:ENV_H // 2], env[:ENV_H // 2])


def test_deterministic(art, tmp_path):
    folder, _ = art
    _run(folder, tmp_path / "a", model="direct")
    _run(folder, tmp_path / "b", model="direct")
    a, b = load_transport(tmp_path / "a", "t0"), load_transport(tmp_path / "b", "t0")
    assert np.array_equal(a.A, b.A) and np.array_equal(a.pixel_index, b.pixel_index)


def test_pooling(art, tmp_path):
    folder, cam = art
    img = np.random.default_rng(0).random((SIZE, SIZE, 3)).astype(np.float32)
    valid = np.ones((SIZE, SIZE), bool)
    valid[3, 5] = False
    pooled, pv = pool_target(img, valid, 2)
    assert pooled.shape == (16, 16, 3) and not pv[1, 2] and pv.sum() == 255
    assert np.allclose(pooled[4, 7], img[8:10, 14:16].mean(axis=(0, 1)))
    _run(folder, tmp_path / "f1", model="direct", samples=16)
    _run(folder, tmp_path / "f2", model="direct", samples=16, downsample=2)
    t1, t2 = load_transport(tmp_path / "f1", "t0"), load_transport(tmp_path / "f2", "t0")
    assert t2.image_shape == (16, 16) and t2.downsample == 2
    x = np.ones((EnvGrid(ENV_H).n_texels, 3), np.float32)
    full = t1.predict(t1.x_from_envmap(t1.envmap_from_x(x[t1.texel_index])))
    p2 = t2.predict(t2.x_from_envmap(t1.envmap_from_x(x[t1.texel_index])))
    want, _ = pool_target(full, np.ones((SIZE, SIZE), bool), 2)
    cov = np.zeros(256)  # compare blocks whose samples all land on surfaces
    cov[t2.pixel_index] = t2.coverage
    inner = t2.kept_mask() & (cov.reshape(16, 16) == 1)
    # measured 0.002 (was bounded at 0.05, which a pooling that takes every other pixel, 0.040, passed)
    assert np.linalg.norm((p2 - want)[inner]) / np.linalg.norm(want[inner]) < 0.01
    # a test of the test (tests/broken.py): the blocks' top-left pixels in place of their means (0.040), and their
    # sums (3.0), miss it
    for bad in (full[::2, ::2], 4 * want):
        assert np.linalg.norm((p2 - bad)[inner]) / np.linalg.norm(want[inner]) >= 0.01


def test_colour_and_unknown_albedo(tmp_path):
    folder = tmp_path / "scene"
    _write_artifact(folder, obj=(0.9, 0.5, 0.2), sup=None)
    _run(folder, tmp_path / "o", model="direct")
    T = load_transport(tmp_path / "o", "t0")
    assert T.channels == 3
    plane = T.object_fraction == 0
    assert T.unknown_albedo[plane].all() and not T.unknown_albedo[T.object_fraction == 1].any()
    assert np.allclose(T.albedo[plane], 1.0)
    obj = T.object_fraction == 1
    assert np.allclose(T.albedo[obj], (0.9, 0.5, 0.2), atol=1e-6)
    # A_c = rho_c A' on object pixels
    ap = T.rho_free()
    assert np.allclose(ap[0][obj], ap[2][obj], rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("indirect", ["gather", "path"])
def test_auto_decides_against_the_noise(art, tmp_path, indirect):
    folder, _ = art
    m = _run(folder, tmp_path / "loud", model="auto", auto_noise=0.5, auto_columns=6, auto_spp=8,
             correction_spp=8)
    assert m["auto_choice"] == "direct" and m["model"] == "direct"
    assert 0.005 < m["auto_relative_indirect"] < 0.5  # a grey 0.8 plane bounces a few % onto the sphere
    m2 = _run(folder, tmp_path / "quiet", model="auto", auto_noise=1e-4, auto_columns=6, auto_spp=8,
              correction_spp=8, indirect=indirect)
    assert m2["auto_choice"] == "direct+indirect" and m2["indirect"] == indirect
    assert (m2["gather_hits"] if indirect == "gather" else m2["correction_renders"]) > 0
    a, b = load_transport(tmp_path / "loud", "t0"), load_transport(tmp_path / "quiet", "t0")
    assert np.array_equal(a.texel_index, b.texel_index)
    extra = (b.A - a.A).sum() / a.A.sum()
    assert 0.0 < extra < 0.5


def test_auto_models_indirect_light_below_the_per_pixel_noise(art, tmp_path):
    """Issue 22: indirect light smaller than one pixel's noise is still a bias shared by every pixel; the
    decision is by its chi-squared effect on the fit (objcam.transport.auto.indirect_effect), so it is modelled."""
    folder, _ = art
    probe = _run(folder, tmp_path / "probe", model="auto", auto_noise=0.5, auto_columns=6, auto_spp=8)
    noise = 2.0 * probe["auto_relative_indirect"]  # per-pixel noise twice the indirect light's relative size
    m = _run(folder, tmp_path / "o", model="auto", auto_noise=noise, auto_columns=6, auto_spp=8)
    assert m["auto_relative_indirect"] < m["auto_target_noise"]  # the old per-pixel test would say "direct"
    assert m["auto_effect_chi2"] > m["auto_threshold_chi2"] and m["auto_margin"] > 1
    assert m["auto_choice"] == "direct+indirect" and m["correction_seconds"] >= 0


def test_indirect_effect_scales_with_pixels_and_noise():
    from objcam.transport.auto import AUTO_EFFECT_Z, indirect_effect

    rng = np.random.default_rng(0)
    direct = rng.uniform(0.5, 1.5, (4000, 3))
    indirect = 0.01 * direct  # 1% everywhere
    eff, thr = indirect_effect(direct, indirect, noise=0.02)  # below the per-pixel noise
    want = np.sum(indirect**2) / (0.02 * np.median(direct)) ** 2
    assert eff == pytest.approx(want) and thr == pytest.approx(AUTO_EFFECT_Z * np.sqrt(2 * direct.size))
    assert eff > thr  # 12,000 pixel values: a 1% bias is a 0.5-sigma shift each, ~3,000 in chi-squared
    eff_few, thr_few = indirect_effect(direct[:20], indirect[:20], noise=0.02)
    assert eff_few < thr_few  # 60 values: the same bias hides in the noise
    assert indirect_effect(direct, indirect, noise=0.0) == (0.0, float("inf"))


def test_pinned_scale_effect_catches_a_bias_the_whole_image_hides():
    """Issue 29: a few pixels of known albedo pin an unknown albedo's scale; indirect light on them (a dark object
    lit by a bright support) biases that scale although the whole image's chi-squared cannot see it."""
    from objcam.transport.auto import AUTO_EFFECT_Z, indirect_effect, pinned_scale_effect

    direct = np.ones((4000, 3))
    pins = np.zeros(4000, bool)
    pins[:200] = True
    indirect = np.where(pins[:, None], 0.05, 0.0)  # 5% more light on the pinning pixels only
    eff, thr = indirect_effect(direct, indirect, noise=0.1)
    assert eff < thr  # 600 values off by half the noise: within the chi-squared's spread over 12,000
    z2, zthr = pinned_scale_effect(direct, indirect, noise=0.1, pins=pins)
    assert zthr == AUTO_EFFECT_Z**2
    assert z2 == pytest.approx((0.05 / (0.1 / np.sqrt(600))) ** 2) and z2 > zthr  # a 12-sigma bias of the scale
    assert pinned_scale_effect(direct, indirect, 0.1, np.zeros(4000, bool)) == (0.0, float("inf"))
    assert pinned_scale_effect(direct, 0.0 * indirect, 0.1, pins)[0] == 0.0


def test_path_model_with_direct_light_only_matches_direct(art, tmp_path):
    folder, _ = art
    m = _run(folder, tmp_path / "p", model="path", path_spp=64, path_max_depth=2, downsample=2)
    _run(folder, tmp_path / "d", model="direct", downsample=2)
    p, d = load_transport(tmp_path / "p", "t0"), load_transport(tmp_path / "d", "t0")
    assert m["model"] == "path" and p.model == "path" and p.spp == 64
    assert np.array_equal(p.pixel_index, d.pixel_index)
    # the same lit directions (the path model may keep a texel just below the horizon whose box-bitmap ramp
    # reaches above it)
    assert set(d.texel_index) <= set(p.texel_index)
    extra = np.setdiff1d(p.texel_index, d.texel_index)
    assert np.all(extra // (2 * ENV_H) == ENV_H // 2)
    pa = p.A[:, :, np.searchsorted(p.texel_index, d.texel_index)]
    # texels next to the horizon differ more: the bitmap's ramps move some light across it, and the camera sees
    # the envmap just below it past the plane's edge (pixel coverage: noisy at 64 spp)
    far = np.abs(d.texel_index // (2 * ENV_H) + 0.5 - ENV_H / 2) > 1
    err = np.linalg.norm(pa[..., far] - d.A[..., far]) / np.linalg.norm(d.A[..., far])
    assert err < 0.05, err  # 64 spp noise (about 3%)
    # a test of the test (tests/broken.py): each path column against the direct column one azimuth texel over
    # (an envmap turned by one texel, 360 / (2 ENV_H) degrees) misses the bound (measured 0.116)
    cols = d.texel_index[far]
    turned = (cols // (2 * ENV_H)) * (2 * ENV_H) + (cols % (2 * ENV_H) + 1) % (2 * ENV_H)
    assert np.isin(turned, p.texel_index).all()
    bad = np.linalg.norm(p.A[:, :, np.searchsorted(p.texel_index, turned)] - d.A[..., far]) / np.linalg.norm(
        d.A[..., far])
    assert not bad < 0.05, bad
    err = np.linalg.norm(pa - d.A) / np.linalg.norm(d.A)
    assert err < 0.2, err


def test_settled_prefix_changes_A_less_than_a_new_seed(model):
    """Pairs traced with all S = 256 rays first trace a 64-ray stratified prefix; where it is unanimous the other
    rays take its verdict (DirectModel._trace_all). On the sphere's 256-sample pixels that skips ~25% of the shadow
    rays, and moves A by a sixth of what a new seed moves it (measured 0.05% against 0.29%)."""
    geo, s16, _ = model
    s = primary_samples(geo, _camera_of(model), 1, 256, np.arange(SIZE * SIZE), SIZE, seed=0)
    s = s.subset(s.hit.any(axis=1))
    tex = np.arange(EnvGrid(ENV_H).n_texels)
    settled = DirectModel(geo, s, ENV_H, 1, rays=16, seed=0, image_shape=(SIZE, SIZE))
    full, full1 = (DirectModel(geo, s, ENV_H, 1, rays=16, seed=sd, image_shape=(SIZE, SIZE), prefix=256)
                   for sd in (0, 1))
    a, b, c = (dm.columns(tex)[0] for dm in (settled, full, full1))
    assert settled.prefix == 64 and settled.stats.pairs_settled > 0.3 * settled.stats.pairs_refined
    assert settled.stats.rays_traced < 0.8 * full.stats.rays_traced
    assert np.linalg.norm(a - b) < 0.5 * np.linalg.norm(c - b), (np.linalg.norm(a - b), np.linalg.norm(c - b))
    assert not np.array_equal(a, b)  # the settled pairs did skip rays


def test_auto_stops_measuring_once_the_choice_is_clear(art, tmp_path, monkeypatch):
    """Issue 25: auto measures its columns in farthest-point order and stops after AUTO_MIN_COLUMNS once the margin
    is beyond AUTO_STOP_MARGIN (or below its inverse); each column keeps the seeds of its rank among the sorted
    columns, so the choice and A are those of the full measurement, for 6 of its 16 columns' renders. A noisy target
    (margin far below 1) stops as well, the other way."""
    import objcam.transport.auto as au

    folder, _ = art
    stop, first = au.AUTO_STOP_MARGIN, au.AUTO_MIN_COLUMNS
    kw = dict(model="auto", auto_columns=16, auto_spp=8)
    quiet = _run(folder, tmp_path / "quiet", auto_noise=1e-4, **kw)
    loud = _run(folder, tmp_path / "loud", auto_noise=5.0, **kw)  # margin after 6: 0.29 at noise 0.5, 0.0029 here
    monkeypatch.setattr(au, "AUTO_STOP_MARGIN", float("inf"))  # the full measurement: every column
    full = _run(folder, tmp_path / "full", auto_noise=1e-4, **kw)
    full_loud = _run(folder, tmp_path / "full_loud", auto_noise=5.0, **kw)
    assert quiet["auto_columns"] == first and full["auto_columns"] == 16
    assert quiet["auto_margin"] >= stop and full["auto_margin"] > 1
    assert quiet["auto_choice"] == full["auto_choice"] == "direct+indirect"
    assert loud["auto_columns"] == first and loud["auto_margin"] <= 1 / stop
    assert loud["auto_choice"] == full_loud["auto_choice"] == "direct"
    a, b = load_transport(tmp_path / "quiet", "t0"), load_transport(tmp_path / "full", "t0")
    assert np.array_equal(a.A, b.A)
    # the measured prefix is the full measurement's first columns: the margin after them is the one the full run
    # logged there (the same seeds), and the full run's 16-column margin is within the 4x the stop allows for
    assert full["auto_margins"][0] == pytest.approx(quiet["auto_margin"], rel=1e-9)
    assert full["auto_margin"] > quiet["auto_margin"] / 25


def test_round_pairs_across_a_horizon_take_all_samples_unshadowed_light(art, monkeypatch):
    """An object pixel whose faceted normals put a texel above some samples' horizon and below others' traces one
    round of K rays; the round's few active rays used to carry the cosines too (the demo: such a pair 2.2x its
    all-sample value). Now the round gives only the visible fraction, times the unshadowed light of all S samples
    (DirectModel._unshadowed, no shadow rays). On the sphere's interior pixels (S = 256, K = 16, no refinement)
    against S = 2048 rays a pair: relative error of those pairs 4.4% -> 2.5% (measured); the bound sits between,
    and the former estimator (``_unshadowed`` disabled) must miss it (a test of the test)."""
    geo, _ = hit_samples(art)
    cam = art[1]

    def samples(n, seed):
        s = primary_samples(geo, cam, 1, n, np.arange(SIZE * SIZE), SIZE, seed=seed)
        return s.subset(s.hit.any(axis=1))

    s256, tex = samples(256, 0), np.arange(EnvGrid(ENV_H).n_texels)
    ref = DirectModel(geo, samples(2048, 5), ENV_H, 1, rays=2048, seed=3, refine=False).columns(tex)[0]
    inner = (s256.on_object & s256.hit).all(axis=1)[:, None]

    def error() -> float:
        dm = DirectModel(geo, s256, ENV_H, 1, rays=16, seed=0, refine=False, image_shape=(SIZE, SIZE))
        a = dm.columns(tex)[0]
        zero, analytic, above = dm.classify(tex)
        sel = inner & ~zero & ~analytic & ~above
        assert sel.sum() > 1000
        return float(np.sqrt(((a - ref)[sel] ** 2).sum() / (ref[sel] ** 2).sum()))

    now = error()
    monkeypatch.setattr(DirectModel, "_unshadowed", lambda self, pix, tex, skip: None)
    before = error()
    assert now < 0.034 < before, (now, before)
