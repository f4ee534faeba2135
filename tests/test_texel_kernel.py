"""transport.texel_kernel: shadow rays into a texel's centre (sharper columns), and ``auto``'s choice per target
(objcam.transport.kernel). The sphere-on-plane scene of tests/test_transport.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.envmap import EnvGrid
from objcam.scene import SceneDescription
from objcam.transport import load_transport
from objcam.transport.direct import DirectModel
from objcam.transport.geometry import SceneGeometry, primary_samples
from objcam.transport.kernel import NARROW
from tests.test_transport import ENV_H, SIZE, _run, _sphere_hit, _write_artifact, art  # noqa: F401 (fixture)


@pytest.fixture(scope="module")
def models(art):  # noqa: F811
    folder, cam = art
    desc = SceneDescription.model_validate_json((folder / "scene.json").read_text())
    geo = SceneGeometry.load(desc, folder, env_height=ENV_H)
    s = primary_samples(geo, cam, 1, 16, np.arange(SIZE * SIZE), SIZE, seed=0)
    s = s.subset(s.hit.any(axis=1))
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


def test_fit_gives_each_target_the_kernel_its_fit_prefers(tmp_path):
    """Two targets of one camera: the sphere's photo made through the narrow A from a lamp at a texel's centre,
    and through the box A from a smooth sky. auto builds both A's (the narrow one exactly texel_kernel=0.25's),
    solves each target on both and keeps per target the lower chi2: narrow for the lamp, box for the sky
    (measured: chi2 1.33 against 1.77 for the lamp, 0.83 against 7.9 for the sky)."""
    folder = tmp_path / "scene"
    _write_artifact(folder, cams=2, noise=0.002)
    _run(folder, tmp_path / "box", model="direct", texel_kernel=1.0)
    _run(folder, tmp_path / "narrow", model="direct", texel_kernel=NARROW)
    tb, tn = load_transport(tmp_path / "box", "t0"), load_transport(tmp_path / "narrow", "t0")
    grid = EnvGrid(ENV_H)
    lamp = np.zeros(grid.n_texels)
    lamp[1 * 2 * ENV_H + 3] = 40.0
    sky = np.where(grid.directions().reshape(-1, 3)[:, 2] > 0, 1.0 + 0.5 * grid.directions().reshape(-1, 3)[:, 0],
                   0.0)
    from objcam.image_io import write_exr

    rng = np.random.default_rng(0)
    for name, tr, env in (("t0", tn, lamp), ("t1", tb, sky)):
        img = tr.predict(np.repeat(env[tr.texel_index, None], 3, axis=1))
        img = img * (1 + 0.002 * rng.standard_normal(img.shape))
        write_exr(folder / "targets" / name / "image.exr", img.astype(np.float32))
    m = _run(folder, tmp_path / "auto", model="direct", texel_kernel="fit")
    rec = m["texel_kernel_auto"]["targets"]
    assert rec["t0"]["kernel"] == NARROW and rec["t0"]["chi2_narrow"] < rec["t0"]["chi2_box"]
    assert rec["t1"]["kernel"] == 1.0 and rec["t1"]["chi2_box"] < rec["t1"]["chi2_narrow"]
    index = json.loads((tmp_path / "auto" / "index.json").read_text())
    assert index["targets"] == {"t0": "cam0k", "t1": "cam0"}
    assert np.array_equal(load_transport(tmp_path / "auto", "t0").A, tn.A)  # the same seeds: the same columns
    assert np.array_equal(load_transport(tmp_path / "auto", "t1").A, tb.A)
    # auto (the default): only the lamp's box solve leaves black sky (measured: 94% of it; the sky's 0), so only
    # it is solved on the narrow A, and takes it
    ma = _run(folder, tmp_path / "auto2", model="direct")
    rec = ma["texel_kernel_auto"]["targets"]
    assert rec["t0"]["dark_sky_area_box"] > 0.5 and rec["t0"]["kernel"] == NARROW
    assert rec["t1"]["dark_sky_area_box"] < 0.02 and rec["t1"]["kernel"] == 1.0 and "chi2_narrow" not in rec["t1"]
    assert json.loads((tmp_path / "auto2" / "index.json").read_text())["targets"] == {"t0": "cam0k", "t1": "cam0"}


def test_fit_drops_an_A_no_target_took_and_refuses_what_it_does_not_build(tmp_path):
    from objcam.errors import StageError

    folder = tmp_path / "scene"
    _write_artifact(folder, cams=1, noise=0.002)  # a flat grey photo: whichever fits, one A is left
    # auto on a smooth sky's photo: nothing black, no second A built
    _run(folder, tmp_path / "box", model="direct", texel_kernel=1.0)
    tb = load_transport(tmp_path / "box", "t0")
    d = EnvGrid(ENV_H).directions().reshape(-1, 3)
    img = tb.predict(np.repeat(np.where(d[:, 2] > 0, 1.0 + 0.5 * d[:, 0], 0.0)[tb.texel_index, None], 3, axis=1))
    sky = tmp_path / "sky"
    _write_artifact(sky, cams=1, noise=0.002)
    from objcam.image_io import write_exr

    write_exr(sky / "targets" / "t0" / "image.exr", img.astype(np.float32))
    m = _run(sky, tmp_path / "default", model="direct")
    assert m["texel_kernel_auto"]["targets"]["t0"]["dark_sky_area_box"] < 0.02 and "seconds_narrow" not in m
    assert sorted(p.name for p in (tmp_path / "default").iterdir() if p.is_dir()) == ["cam0"]
    m = _run(folder, tmp_path / "auto", model="direct", texel_kernel="fit")
    kept = sorted(p.name for p in (tmp_path / "auto").iterdir() if p.is_dir())
    assert len(kept) == 1 and kept[0] == ("cam0k" if m["texel_kernel_auto"]["targets"]["t0"]["kernel"] < 1
                                          else "cam0")
    with pytest.raises(StageError, match="texel_kernel=fit"):
        _run(folder, tmp_path / "ss", model="direct", texel_kernel="fit", supersample=2)
