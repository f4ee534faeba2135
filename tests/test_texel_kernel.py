"""transport.texel_kernel: shadow rays into a texel's centre (sharper columns), and ``auto``'s choice per target
(objcam.transport.kernel). The sphere-on-plane scene of tests/test_transport.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.envmap import EnvGrid
from objcam.transport import load_transport
from objcam.transport.direct import DirectModel
from objcam.transport.kernel import NARROW
from tests.test_transport import ENV_H, SIZE, _run, _sphere_hit, _write_artifact, art, hit_samples  # noqa: F401


@pytest.fixture(scope="module")
def models(art):  # noqa: F811
    geo, s = hit_samples(art)
    box = DirectModel(geo, s, ENV_H, 1, rays=4, seed=0, image_shape=(SIZE, SIZE))
    narrow = DirectModel(geo, s, ENV_H, 1, rays=4, seed=0, image_shape=(SIZE, SIZE), kernel=NARROW)
    return s, box, narrow


def test_a_narrow_kernel_sharpens_shadows_and_keeps_the_unshadowed_light(models):
    """Plane pixels: where no ray into the texel's central part can meet the sphere the narrow column is the
    exact unshadowed integral (as the box's), where every such ray does it is 0; and fewer pixels are half lit
    (the penumbra of a 1.4-deg kernel against the box's 5.6-deg one at 32 rows; at 8 rows here, 5.6 against
    22.5 deg)."""
    s, box, narrow = models
    grid = EnvGrid(ENV_H)
    tex = np.arange(grid.n_texels)
    A, B = box.columns(tex)[0], narrow.columns(tex)[0]
    plane = np.nonzero((~s.on_object & s.hit).all(axis=1))[0]
    rng = np.random.default_rng(1)
    u, v = rng.random(96), rng.random(96)
    uc, vc = 0.5 + NARROW * (u - 0.5), 0.5 + NARROW * (v - 0.5)  # the central part, per side
    half_box = half_narrow = checked = 0
    for r in (1, 2):
        for c in range(0, 2 * ENV_H):
            j = r * 2 * ENV_H + c
            w = grid.sample_in_texels(uc, vc, np.full(96, r), np.full(96, c))
            o = s.pos[plane][:, :, None, :]
            big = _sphere_hit(o, w[None, None], 0.1 * 1.01).reshape(len(plane), -1)
            small = _sphere_hit(o, w[None, None], 0.1 * 0.98).reshape(len(plane), -1)
            unocc = (0.8 / np.pi) * box.tab.wvec[j, 2]
            lit, umbra = ~big.any(axis=1), small.all(axis=1)
            assert np.allclose(B[plane[lit], j], unocc, rtol=1e-4)
            assert np.all(B[plane[umbra], j] == 0)
            checked += umbra.sum()
            half_box += np.sum((A[plane, j] > 0.02 * unocc) & (A[plane, j] < 0.98 * unocc))
            half_narrow += np.sum((B[plane, j] > 0.02 * unocc) & (B[plane, j] < 0.98 * unocc))
    assert checked > 5
    assert half_narrow < 0.6 * half_box  # measured: 0.44
    # where nothing can shadow the pixel, both kernels give the same exact value
    far = np.linalg.norm(s.pos[plane, :, :2].mean(axis=1), axis=1) > 1.5
    assert np.allclose(A[plane[far]], B[plane[far]], rtol=1e-5, atol=1e-9)


def _photos(folder, trs_envs, seed=0):
    from objcam.image_io import write_exr

    rng = np.random.default_rng(seed)
    for name, tr, env in trs_envs:
        img = tr.predict(np.repeat(env[tr.texel_index, None], 3, axis=1))
        img = img * (1 + 0.002 * rng.standard_normal(img.shape))
        write_exr(folder / "targets" / name / "image.exr", img.astype(np.float32))


def _lamp_and_sky():
    grid = EnvGrid(ENV_H)
    lamp = np.zeros(grid.n_texels)
    lamp[1 * 2 * ENV_H + 3] = 40.0
    d = grid.directions().reshape(-1, 3)
    return lamp, np.where(d[:, 2] > 0, 1.0 + 0.5 * d[:, 0], 0.0)


def test_fit_gives_each_target_the_kernel_its_fit_prefers(tmp_path, monkeypatch):
    """Two targets of one camera, photos made through the narrow A: a lamp at a texel's centre and a smooth sky.
    fit solves each on the box A, the narrow A (exactly texel_kernel=0.25's: the same seeds) and, for the lamp, the
    box A with narrow columns at its compact bright blob and the box A with a point source placed by the photo.
    The lamp's point source beats box texels (measured: chi2 1.65 against 1.79 over the pixels every candidate
    fitted), which sets the compact columns aside (objcam.transport.kernel.pick; they tie with the narrow A here,
    0.8783 both), and the narrow A, the
    photo's own, fits best; the sky takes the narrow A (no blob, so no compact or point A). The default (auto)
    asks only the lamp, whose box solve left black sky (94% of it), and keeps the sky on box texels. The pilots
    at the fixed ridge the chi2s were measured at (lr 1e-4)."""
    from objcam.solvers.regularization import DEFAULT_LR_REL

    monkeypatch.setattr("objcam.solvers.plan.rules.noise_lr", lambda sigma: DEFAULT_LR_REL)
    folder = tmp_path / "scene"
    _write_artifact(folder, cams=2, noise=0.002)
    _run(folder, tmp_path / "box", model="direct", texel_kernel=1.0)
    _run(folder, tmp_path / "narrow", model="direct", texel_kernel=NARROW)
    tb, tn = load_transport(tmp_path / "box", "t0"), load_transport(tmp_path / "narrow", "t0")
    lamp, sky = _lamp_and_sky()
    _photos(folder, (("t0", tn, lamp), ("t1", tn, sky)))
    m = _run(folder, tmp_path / "fit", model="direct", texel_kernel="fit")
    rec = m["texel_kernel_auto"]["targets"]
    assert rec["t0"]["kernel"] == "narrow"
    assert rec["t0"]["chi2_point"] < rec["t0"]["chi2_box"] * (1.0 - 0.02)
    assert rec["t0"]["chi2_narrow"] < 0.9 * rec["t0"]["chi2_point"]
    assert rec["t0"]["chi2_compact"] < 0.9 * rec["t0"]["chi2_box"]
    assert rec["t1"]["kernel"] == "narrow" and rec["t1"]["chi2_narrow"] < rec["t1"]["chi2_box"]
    assert "chi2_compact" not in rec["t1"]  # a smooth sky has no compact blob
    index = json.loads((tmp_path / "fit" / "index.json").read_text())["targets"]
    assert index["t1"] == "cam0k" and np.array_equal(load_transport(tmp_path / "fit", "t1").A, tn.A)
    # the compact A, taken by a pick told to: box columns, but narrow ones at the lamp's blob, its Gram updated
    with monkeypatch.context() as told:
        told.setattr("objcam.transport.kernel.pick", lambda res, names, joint: {"t0": "compact", "t1": "narrow"})
        _run(folder, tmp_path / "fitc", model="direct", texel_kernel="fit")
    index = json.loads((tmp_path / "fitc" / "index.json").read_text())["targets"]
    assert index["t0"] == "cam0c"
    tc = load_transport(tmp_path / "fitc", "t0")
    at = np.isin(tc.texel_index, tc.attrs["narrow_texels"])
    assert 0 < at.sum() < tc.n_texels and lamp.argmax() in tc.attrs["narrow_texels"]
    assert np.allclose(tc.A[:, :, at], tn.A[:, :, at], rtol=1e-5, atol=1e-7)
    assert np.array_equal(tc.A[:, :, ~at], tb.A[:, :, ~at])
    G = tc.gram()
    assert np.allclose(G[0], tc.A[0].astype(np.float64).T @ tc.A[0].astype(np.float64), rtol=1e-6, atol=1e-9)
    # auto (the default): only the lamp's box solve leaves black sky; the sky stays on box texels
    ma = _run(folder, tmp_path / "auto", model="direct")
    rec = ma["texel_kernel_auto"]["targets"]
    assert rec["t0"]["dark_sky_area_box"] > 0.5 and rec["t0"]["kernel"] in ("compact", "narrow")
    assert rec["t1"]["dark_sky_area_box"] < 0.02 and rec["t1"]["kernel"] == "box" and "chi2_narrow" not in rec["t1"]


def test_a_smooth_sky_on_box_texels_keeps_them_and_fit_refuses_what_it_does_not_build(tmp_path):
    from objcam.errors import StageError

    folder = tmp_path / "scene"
    _write_artifact(folder, cams=1, noise=0.002)
    _run(folder, tmp_path / "box", model="direct", texel_kernel=1.0)
    _photos(folder, (("t0", load_transport(tmp_path / "box", "t0"), _lamp_and_sky()[1]),))
    m = _run(folder, tmp_path / "auto", model="direct")  # auto: nothing black, no blob: no second A built
    rec = m["texel_kernel_auto"]["targets"]["t0"]
    assert rec["dark_sky_area_box"] < 0.02 and rec["kernel"] == "box" and set(rec) == {
        "dark_sky_area_box", "kernel", "chi2_box", "chi2_own_box", "values_compared"}
    assert "seconds_narrow" not in m and "compact_texels" not in m
    assert sorted(p.name for p in (tmp_path / "auto").iterdir() if p.is_dir()) == ["cam0"]
    m = _run(folder, tmp_path / "fit", model="direct", texel_kernel="fit")  # the narrow A built, solved, dropped
    rec = m["texel_kernel_auto"]["targets"]["t0"]
    assert rec["kernel"] == "box" and rec["chi2_box"] < rec["chi2_narrow"]
    assert sorted(p.name for p in (tmp_path / "fit").iterdir() if p.is_dir()) == ["cam0"]
    with pytest.raises(StageError, match="texel_kernel=fit"):
        _run(folder, tmp_path / "ss", model="direct", texel_kernel="fit", supersample=2)


def test_compact_blobs_are_lamps_not_windows():
    """A blob of at most 9 texels above 10x the sky's median (grown by one texel, azimuth wrapping) is compact; a
    window-sized bright area is not."""
    from objcam.transport.kernel import compact_blobs

    env = np.ones((32, 64, 3))
    mask = np.ones((32, 64), bool)
    env[10, 63] = env[10, 0] = 50.0  # a lamp across the seam
    env[4:10, 20:32] = 30.0  # a window: 72 texels
    b = compact_blobs(env, mask)
    assert b[10, 63] and b[10, 0] and b[9, 62] and b[11, 1] and b.sum() == 3 * 4
    assert not b[4:10, 20:32].any()
    mask[10, 0] = False
    assert not compact_blobs(env, mask)[10, 0]  # unsolved texels are never chosen
    assert not compact_blobs(np.zeros_like(env), mask).any()


def test_auto_keeps_box_texels_where_an_albedo_is_unknown(tmp_path):
    """The joint solve is not repeated per candidate under auto (its cost), and says so; one A, box texels."""
    folder = tmp_path / "scene"
    _write_artifact(folder, sup=None, cams=1, noise=0.002)
    m = _run(folder, tmp_path / "auto", model="direct")
    assert "unknown albedo" in m["texel_kernel_auto"]["skipped"]
    assert sorted(p.name for p in (tmp_path / "auto").iterdir() if p.is_dir()) == ["cam0"]


def test_pick_keeps_box_texels_unless_a_candidate_fits_better_than_the_chi2_spread():
    """A candidate replaces box texels only where its chi2 per value is lower by more than the chi-squared's spread
    (sqrt(2 / n) x box's: 0.0063 x 1.2 for n = 50,000), and the lowest chi2 among those wins, except that a point
    source that beats box texels is kept over the compact kernel's better fit (objcam.transport.kernel: the mix of
    narrow columns splits the source); the joint pick sums the fits."""
    from objcam.transport.kernel import pick

    n = 50_000
    spread = 1.2 * np.sqrt(2.0 / n)  # 0.0076
    res = {"box": {"a": {"chi2": 1.2, "values": n}, "b": {"chi2": 1.2, "values": n}},
           "point": {"a": {"chi2": 1.2 - 0.5 * spread, "values": n}, "b": {"chi2": 1.2 - 2 * spread, "values": n}},
           "compact": {"a": {"chi2": 1.2 - 3 * spread, "values": n}, "b": {"chi2": 1.2 - 3 * spread, "values": n}},
           "narrow": {"b": {"chi2": 1.2 - 4 * spread, "values": n}}}
    # a: point within the spread, so the compact kernel's fit decides; b: point beats box, narrow beats it
    assert pick(res, ["a", "b"], joint=False) == {"a": "compact", "b": "narrow"}
    res["narrow"]["b"]["chi2"] = 1.2 - 1.5 * spread
    assert pick(res, ["a", "b"], joint=False) == {"a": "compact", "b": "point"}
    del res["compact"], res["narrow"]
    assert pick(res, ["a", "b"], joint=False) == {"a": "box", "b": "point"}
    # joint: the summed misfit drops by 1.77 spreads of the summed box fit's (sqrt(2 / 2n) x 2.4 n), then by 0.99
    assert pick(res, ["a", "b"], joint=True) == {"a": "point", "b": "point"}
    res["point"]["b"]["chi2"] = 1.2 - 0.9 * spread
    assert pick(res, ["a", "b"], joint=True) == {"a": "box", "b": "box"}


def test_candidates_are_compared_on_the_same_pixels_those_every_one_of_them_fitted():
    """Each pilot solve drops its own outliers, so box texels that cannot draw a sharp shadow drop its edge, while a
    point source that explains the edge better (within the outlier threshold) keeps it and pays for it in its own
    chi2. kernel.on_common_pixels scores every candidate over the pixels all of them fitted, where the point fits
    better and wins; the test's test: on their own pixels box texels would be kept."""
    from objcam.transport.kernel import on_common_pixels, pick

    rng = np.random.default_rng(3)
    m, sigma = 20_000, 0.01
    y = np.full((m, 3), 1.0) + rng.normal(0.0, sigma, (m, 3))  # the photo: median 1, so sigma_abs = sigma
    edge = np.zeros(m, bool)
    edge[:400] = True  # a shadow's edge: box texels miss it by 10 sigma and drop it, the point by 5 and keep it
    fly = np.zeros(m, bool)
    fly[400:410] = True  # fireflies: every candidate misses them by 1000 sigma and drops them
    y[fly] += 10.0
    box_pred = 1.0 + np.where(edge, 10 * sigma, 0.3 * sigma)[:, None] * np.ones(3)
    point_pred = 1.0 + np.where(edge, 5 * sigma, 0.2 * sigma)[:, None] * np.ones(3)

    def result(pred, dropped):
        r = (y - pred)[~dropped]
        return {"chi2": float(np.mean((r / sigma) ** 2)), "values": m * 3, "y": y, "pred": pred,
                "fitted": ~dropped, "noise": sigma}

    res = {"box": {"t": result(box_pred, edge | fly)}, "point": {"t": result(point_pred, fly)}}
    assert res["box"]["t"]["chi2"] < 1.2 < 1.4 < res["point"]["t"]["chi2"]  # on their own pixels box fits better
    assert pick(res, ["t"], joint=False) == {"t": "box"}  # ... and would be kept (the test's test)
    on_common_pixels(res, ["t"])
    assert res["box"]["t"]["values"] == res["point"]["t"]["values"] == (m - 410) * 3  # edge and fireflies out
    assert res["point"]["t"]["chi2"] < 0.98 * res["box"]["t"]["chi2"]
    assert res["box"]["t"]["chi2_own"] < res["point"]["t"]["chi2_own"]  # the solves' own kept for the record
    assert pick(res, ["t"], joint=False) == {"t": "point"}


def test_a_candidates_columns_and_gram_match_a_rebuilt_a_and_the_box_a_is_left_as_it_was():
    """kernel.replace_direct keeps a candidate as its changed columns (no copy of A): its Gram matrix must equal
    the Gram of the A rebuilt with those columns (to float64 rounding), ``swapped`` must show that A inside and
    give the box A back afterwards, even when the pilot inside fails. Broken versions this catches: the Gram's
    (pos, pos) block left as A_old^T A_new (off by delta^T a_new, ~1e-2 here), or A not restored."""
    from objcam.solvers import gram
    from objcam.transport.kernel import replace_direct, swapped
    from tests.toy_scenes import sphere_shadow_toy

    tr, _ = sphere_shadow_toy(EnvGrid(8), 12)
    box = tr.A.copy()
    tr._gram = np.stack([gram(tr.A[0])])
    rng = np.random.default_rng(3)
    pos = np.array([2, 5, 6, 30])
    delta = (0.02 * rng.standard_normal((1, tr.n_pixels, pos.size))).astype(np.float32)
    cand = replace_direct(tr, pos, delta)
    rebuilt = box.copy()
    rebuilt[:, :, pos] += delta
    want = gram(rebuilt[0])
    assert np.array_equal(tr.A, box)  # the candidate did not touch A
    assert np.abs(cand.gram[0] - want).max() <= 1e-12 * np.abs(want).max()
    assert np.array_equal(cand.gram[0], cand.gram[0].T)
    with swapped(tr, cand) as t2:
        assert np.array_equal(t2.A, rebuilt) and t2.gram() is cand.gram
    assert np.array_equal(tr.A, box)
    with pytest.raises(RuntimeError):
        with swapped(tr, cand):
            raise RuntimeError("a pilot that fails")
    assert np.array_equal(tr.A, box)


def test_write_columns_replaces_only_the_candidates_columns(tmp_path):
    """storage.write_columns copies a group and sets the given columns (across two column chunks) and the Gram."""
    import zarr

    from objcam.transport.storage import write_columns

    src = tmp_path / "src"
    g = zarr.open_group(str(src), mode="w", zarr_format=3)
    A = np.arange(2 * 5 * 10, dtype=np.float32).reshape(2, 5, 10)
    g.create_array("A", shape=A.shape, chunks=(2, 5, 4), dtype=np.float32)[...] = A
    g.create_array("texel_index", shape=(10,), dtype=np.int64)[...] = np.arange(100, 110)
    pos = np.array([1, 6, 9])
    cols = -np.ones((2, 5, 3), np.float32) * np.array([1, 2, 3], np.float32)
    write_columns(src, tmp_path / "dst", pos, cols, np.eye(10)[None].repeat(2, 0))
    out = zarr.open_group(str(tmp_path / "dst"), mode="r")
    want = A.copy()
    want[:, :, pos] = cols
    assert np.array_equal(out["A"][...], want)
    assert out.attrs["narrow_texels"] == [101, 106, 109]
    assert np.array_equal(np.load(tmp_path / "dst" / "gram.npy"), np.eye(10)[None].repeat(2, 0))
    assert np.array_equal(zarr.open_group(str(src), mode="r")["A"][...], A)  # the source is left as it was
