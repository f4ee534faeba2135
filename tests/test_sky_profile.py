"""objcam.solvers.skyprofile (solve.sky_profile=auto, issues 22 and 28): azimuthal detail in the dim sky that the
photo cannot tell from none gives way to the map's own profile per elevation row; detail the photo does see
stays."""

from __future__ import annotations

import numpy as np
import pytest

from objcam.envmap import EnvGrid
from objcam.metrics import ssim, tonemap, tonemap_scale
from objcam.solvers.skyprofile import row_profile, sky_profile
from tests.toy_scenes import lobe_scene

H = 16


def _scene(seed: int, visibility: float | None):
    """tests.toy_scenes.lobe_scene on a 16 x 32 grid, with the kept texels' solid angles (sr)."""
    grid, texel_index, A, rng = lobe_scene(seed, visibility, H)
    return grid, texel_index, A, grid.solid_angles().reshape(-1)[texel_index], rng


def _data(A: np.ndarray, x: np.ndarray, rng, noise: float = 0.01) -> np.ndarray:
    y = A[0].astype(np.float64) @ x
    return y + noise * np.median(y) * rng.normal(size=y.shape)


def _tm_ssim(x: np.ndarray, truth: np.ndarray, texel_index: np.ndarray) -> float:
    def env(v):
        e = np.zeros((H * 2 * H, 3))
        e[texel_index] = v
        return e.reshape(H, 2 * H, 3)

    s = tonemap_scale(env(truth))
    return ssim(tonemap(env(x), s), tonemap(env(truth), s))


def test_row_profile_keeps_each_rows_energy_and_leaves_the_rest():
    grid = EnvGrid(8)
    ti = np.arange(grid.n_texels)
    rows = ti // grid.width
    omega = grid.solid_angles().reshape(-1)
    rng = np.random.default_rng(3)
    x = rng.random((ti.size, 3))
    sky = rng.random(ti.size) < 0.8
    out = row_profile(x, rows, sky, omega)
    np.testing.assert_array_equal(out[~sky], x[~sky])
    for r in range(grid.height):
        sel = sky & (rows == r)
        if sel.any():
            np.testing.assert_allclose((out[sel] * omega[sel, None]).sum(0), (x[sel] * omega[sel, None]).sum(0))
            assert np.ptp(out[sel], axis=0).max() == 0.0


def test_patches_the_photo_cannot_see_give_way_to_the_profile():
    grid, ti, A, omega, rng = _scene(0, None)
    W = grid.width
    row, col = ti // W, ti % W
    truth = np.repeat(0.2 + 0.1 * row[:, None], 3, axis=1)  # a dim sky that varies with elevation only
    lamp = 2 * W + 9
    truth[lamp] += 300.0
    y = _data(A, truth, rng)
    # what the edge prior draws: azimuthal patches in the dim sky, a third harmonic the Lambertian photo is
    # blind to (the lamp and its rim as solved)
    patched = truth * (1.0 + 0.6 * np.sin(3 * 2 * np.pi * (col + 0.5) / W))[:, None]
    patched[lamp] = truth[lamp]
    use = np.ones(y.shape[0], bool)
    got = sky_profile(A, use, y, patched, grid, ti, np.ones(ti.size, bool), omega)
    assert got.info["taken"] and got.info["blobs"] == 1 and got.info["source_texels"] == 9
    assert got.info["ss_profile"] - got.info["ss_map"] <= got.info["ss_spread"]
    assert got.x[lamp, 0] == patched[lamp, 0]  # the source is kept as solved
    before, after = _tm_ssim(patched, truth, ti), _tm_ssim(got.x, truth, ti)
    assert after > 0.98 and after > before + 0.1, (before, after)  # measured 0.861 -> 0.990


def test_a_sky_the_photo_sees_in_azimuth_is_left_alone():
    grid, ti, A, omega, rng = _scene(1, 0.5)
    W = grid.width
    col = ti % W
    truth = np.where((col < W // 2)[:, None], 4.0, 1.0) * np.ones((ti.size, 3))  # a bright side and a dim side
    y = _data(A, truth, rng)
    use = np.ones(y.shape[0], bool)
    got = sky_profile(A, use, y, truth, grid, ti, np.ones(ti.size, bool), omega)
    assert not got.info["taken"] and got.info["blobs"] == 0
    assert got.info["rise_over_spread"] > 100
    np.testing.assert_array_equal(got.x, truth)


def test_unsolved_texels_stay_unsolved_and_out_of_the_means():
    grid, ti, A, omega, rng = _scene(2, None)
    W = grid.width
    truth = np.repeat(0.5 + 0.05 * (ti // W)[:, None], 3, axis=1)
    y = _data(A, truth, rng)
    solved = np.ones(ti.size, bool)
    solved[ti // W == 7] = False  # the row next to the horizon held out (weak_texels=exclude)
    x = np.where(solved[:, None], truth, 0.0)
    got = sky_profile(A, np.ones(y.shape[0], bool), y, x, grid, ti, solved, omega)
    assert np.all(got.x[~solved] == 0.0)
    if got.info["taken"]:
        np.testing.assert_allclose(got.x[solved], truth[solved], rtol=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_test_of_the_test_a_blind_threshold_would_flatten_a_seen_sky(seed):
    """What the spread rule protects: the same seen sky replaced by its profile raises the misfit by far more
    than the noise (so a rule that took the profile regardless would fail the test above)."""
    grid, ti, A, omega, rng = _scene(1 + seed, 0.5)
    W = grid.width
    truth = np.where((ti % W < W // 2)[:, None], 4.0, 1.0) * np.ones((ti.size, 3))
    y = _data(A, truth, rng)
    prof = row_profile(truth, ti // W, np.ones(ti.size, bool), omega)
    r0, r1 = y - A[0].astype(np.float64) @ truth, y - A[0].astype(np.float64) @ prof
    assert np.sum(r1 * r1) > 10 * np.sum(r0 * r0)


def test_the_known_solve_takes_the_profile_and_solves_on_it():
    """Pipeline level of the step (objcam.solvers.plan.known): a lamp over a sky that varies with elevation only,
    shadows of three spheres on a plane at 1% noise. The edge solve's patches give way to the profile model, solved
    again on it (one unknown per sky row): its rows are flat, the lamp where it was, the fit exact, and the map
    closer to the truth than the solve's own (measured 0.550 -> 0.637). Broken: sky_profile=off keeps the patches."""
    grid = EnvGrid(H)
    truth, keep, (on, off) = _lamp_solves(grid, {(2, 9): 200.0}, 0.01, 0)  # a lamp ~22 deg from the zenith
    rec = on.info["edges"]["sky_profile"]
    assert rec["taken"] and rec["resolved"]["unknowns"] < len(keep) // 4
    assert on.info["kkt_residual_max"] < 1e-6 and "sky_profile" not in off.info["edges"]
    rows = keep // grid.width
    lum = on.envmap.reshape(-1, 3)[keep].mean(axis=1)
    for r in np.unique(rows[on.profile]):
        assert np.ptp(lum[on.profile & (rows == r)]) <= 1e-9 * lum.max()
    peak = np.unravel_index(int(np.argmax(on.envmap[..., 1])), truth.shape[:2])
    assert abs(peak[0] - 2) <= 1 and abs(peak[1] - 9) <= 1  # the lamp within a texel
    s_on = _tm_ssim_env(on.envmap, truth, keep)
    s_off = _tm_ssim_env(off.envmap, truth, keep)
    assert s_on > 0.6 and s_on > s_off + 0.05, (s_off, s_on)


def test_the_profile_is_tested_on_its_own_fit_not_on_the_maps_row_means():
    """A lamp spread over three texels near the horizon at 0.5% noise: the solved map's row means misfit by six
    spreads (the patches carried part of the lamp's shadows), the profile model fitted on the same pixels by the same
    prior fits no worse than one spread above (measured 6.08 -> -0.88 at edge_tone 0.3, 6.4 -> -1.69 at the
    tonemap's 0.545: better than the map), so the profile is taken and solved; its map is closer to the
    truth (tonemapped SSIM 0.914 -> 0.951). Broken: testing only the row means (the step before session 31) or
    sky_profile=off keeps the patches. At the ridge the step was measured with (lr 1e-4; the noise's ridge, 2.5e-5
    here, leaves the map's row means within a spread, so step 3 takes the profile before 3b is asked)."""
    grid = EnvGrid(H)
    truth, keep, (on, off) = _lamp_solves(grid, {(7, 3): 120.0, (7, 4): 80.0, (8, 3): 40.0}, 0.005, 1, lr=1e-4)
    rec = on.info["edges"]["sky_profile"]
    assert rec["rise_over_spread"] > 3.0  # the row means alone: not taken
    assert rec["fitted_rise_over_spread"] <= 1.0 and rec["taken"] and "resolved" in rec
    assert on.profile is not None and on.profile.sum() > len(keep) // 2
    s_on, s_off = _tm_ssim_env(on.envmap, truth, keep), _tm_ssim_env(off.envmap, truth, keep)
    assert s_on > s_off + 0.02, (s_off, s_on)


def test_the_profile_model_s_fit_is_its_better_member_the_row_means_included(monkeypatch):
    """Step 3b's fit is the better of two members of the profile model: the envmap solved on it at the map's prior
    and the map's own row means. A lamp near the zenith over a sky at 0.5% noise: the row means misfit by a few
    spreads, within the map's excess beyond its noise; the solved member is made to fit far worse (its light
    scaled 1.5x, as the hard suite's lamp85_r0_n2's solved member fitted 199 spreads above the map where its row
    means fitted 20.7): the row means keep the profile, the map is solved on it (step 4, unchanged) and comes
    closer to the truth than the edge solve's (measured 0.637 -> 0.674). The test's test: the solved member alone
    lies beyond the allowance (the rule before session 46 kept the patches)."""
    from objcam.solvers.plan import known

    orig = known.solve_known_edges

    def worse_member(*args, **kwargs):
        out = orig(*args, **kwargs)
        if "basis" in kwargs and "sky_rows" not in kwargs:  # step 3b's solve of the profile model
            return (1.5 * out[0],) + tuple(out[1:])
        return out

    monkeypatch.setattr(known, "solve_known_edges", worse_member)
    grid = EnvGrid(H)
    truth, keep, (on, off) = _lamp_solves(grid, {(0, 5): 300.0, (1, 5): 100.0}, 0.005, 0)
    rec = on.info["edges"]["sky_profile"]
    allowed = rec["ss_allowed"] / rec["ss_spread"]
    assert 1.0 < rec["rise_over_spread"] <= allowed < rec["fitted_rise_over_spread"]
    assert rec["model_rise_over_spread"] == pytest.approx(rec["rise_over_spread"])
    assert rec["taken"] and "resolved" in rec and on.profile is not None
    s_on, s_off = _tm_ssim_env(on.envmap, truth, keep), _tm_ssim_env(off.envmap, truth, keep)
    assert s_on > s_off + 0.02, (s_off, s_on)


def _lamp_solves(grid: EnvGrid, lamp: dict, noise: float, seed: int, **params) -> tuple:
    """(truth (H, 2H, 3), A's texels, the known solves at sky_profile auto and off) of a lamp (texel (row, col) ->
    radiance added) over a sky that varies with elevation only, shadows of three spheres on a plane, ``noise``
    relative Gaussian noise (tests.toy_scenes.sphere_shadow_toy); ``params``: more SolveParams."""
    from types import SimpleNamespace

    from objcam.solvers.plan.known import _solve_target
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.targets import TargetData
    from tests.toy_scenes import sphere_shadow_toy

    tr, keep = sphere_shadow_toy(grid, 40)
    theta, _ = grid.centres()
    truth = np.repeat((0.05 + 0.05 * np.cos(theta))[..., None], 3, axis=2)
    for (r, c), v in lamp.items():
        truth[r, c] += v
    clean = tr.predict(tr.x_from_envmap(truth))
    rng = np.random.default_rng(seed)
    photo = clean + noise * np.median(clean[clean > 0]) * rng.normal(size=clean.shape)
    y = photo.reshape(-1, 3)[tr.pixel_index].astype(np.float64)
    d = TargetData(tr, photo, np.ones(photo.shape[:2], bool), y, np.ones(len(y), bool))
    target = SimpleNamespace(noise_sigma=noise, name="t")
    return truth, keep, [_solve_target(target, d, SolveParams(sky_profile=m, **params), {}) for m in ("auto", "off")]


def _tm_ssim_env(env: np.ndarray, truth: np.ndarray, keep: np.ndarray) -> float:
    mask = np.zeros(truth.shape[:2], bool)
    mask.reshape(-1)[keep] = True
    s = tonemap_scale(truth, mask)
    return ssim(tonemap(np.where(mask[..., None], env, 0), s), tonemap(np.where(mask[..., None], truth, 0), s))


def test_the_summary_names_the_targets_that_took_the_profile():
    from objcam.solvers.plan.summary import sky_profile_phrase

    per = {"a": {"edges": {"sky_profile": {"taken": True}}}, "b": {"edges": {"sky_profile": {"taken": False}}},
           "c": {"edges": {}}, "d": {}}
    assert "one value per elevation row for a (" in sky_profile_phrase(per)
    assert sky_profile_phrase({"b": per["b"], "c": per["c"]}) == ""


def test_misfit_allowance_is_the_spread_or_the_maps_excess_over_its_noise():
    from objcam.solvers.skyprofile import misfit_allowance

    # 20,000 values at sigma 0.01: honest noise leaves at most 20,000 x sigma^2 = 2.0 (unfitted)
    assert misfit_allowance(1.9, 20_000, 0.01) == pytest.approx((0.01 * 1.9, 0.0))  # within the noise: the spread
    allow, excess = misfit_allowance(2.8, 20_000, 0.01)
    assert excess == pytest.approx(0.8) and allow == pytest.approx(0.8)  # model error: 0.8 beyond the noise
    assert misfit_allowance(2.01, 20_000, 0.01) == pytest.approx((0.0201, 0.01))  # a small excess: the spread
    assert misfit_allowance(2.8, 20_000, None) == pytest.approx((0.028, 0.0))  # noise unknown: the spread


def _lobe_solves(noise: float, seed: int, normal_error: float, sky_step: float, broken: bool = False) -> tuple:
    """A light object's shading: 900 pixels of random normals (clamped cosine lobes) with a random 0/1 visibility
    per (pixel, texel), under a lamp over a sky that varies with elevation (plus ``sky_step`` x 0.05 on one half of
    the azimuths). The photo is made with the normals off by ``normal_error`` (a wrong mesh: model error the map
    cannot express) and ``noise`` relative Gaussian noise; returns (truth (H, 2H, 3), kept texels, the known solves
    at sky_profile auto and off). ``broken``: step 3b's allowance without the map's excess (the session-31 rule)."""
    from types import SimpleNamespace

    from objcam.solvers.plan import known
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.targets import TargetData
    from tests.toy_scenes import toy_transport

    grid = EnvGrid(H)
    keep = np.arange(grid.n_texels // 2)
    d, om = grid.directions().reshape(-1, 3)[keep], grid.solid_angles().reshape(-1)[keep]
    rng = np.random.default_rng(seed)
    side = 30
    n = rng.normal(size=(side * side, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.5
    vis = rng.random((n.shape[0], keep.size)) < 0.7
    n2 = n / np.linalg.norm(n, axis=1, keepdims=True) + normal_error * rng.normal(size=n.shape)
    A, A_true = (np.maximum((v / np.linalg.norm(v, axis=1, keepdims=True)) @ d.T, 0) * om * vis for v in (n, n2))
    theta, phi = grid.centres()
    truth = np.repeat((0.05 + 0.05 * np.cos(theta) + sky_step * 0.05 * (np.cos(phi) > 0))[..., None], 3, axis=2)
    truth[3, 9] += 300.0
    clean = A_true @ truth.reshape(-1, 3)[keep]
    y = clean + noise * np.median(clean) * rng.normal(size=clean.shape)
    tr = toy_transport(A, grid, keep, side)
    data = TargetData(tr, y.reshape(side, side, 3), np.ones((side, side), bool), y, np.ones(y.shape[0], bool))
    target = SimpleNamespace(noise_sigma=noise, name="t")
    if broken:
        spread_only = lambda ss, values, *_: (float(np.sqrt(2.0 / values) * ss), 0.0)  # noqa: E731
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(known, "misfit_allowance", spread_only)
            on = known._solve_target(target, data, SolveParams(sky_profile="auto"), {})
    else:
        on = known._solve_target(target, data, SolveParams(sky_profile="auto"), {})
    return truth, keep, on, known._solve_target(target, data, SolveParams(sky_profile="off"), {})


@pytest.mark.parametrize("seed", [0, 1])
def test_a_profile_within_the_maps_own_model_error_is_taken(seed):
    """A wrong mesh (normals 1% off) at 0.5% noise: the solved map misfits by ~32 spreads beyond its noise, and the
    profile model's own fit misfits by about 4 spreads more than the map (measured 4.09 / 3.79): within the error
    the map's patches had to spend, so the profile is taken and solved, and its map is far closer to the truth
    (tonemapped SSIM 0.58 -> 0.91, 0.52 -> 0.93 with step 5; 0.86 / 0.90 without it). Broken: the allowance of one
    spread (session 31) keeps the patches."""
    truth, keep, on, off = _lobe_solves(0.005, seed, 0.01, 0.0)
    rec = on.info["edges"]["sky_profile"]
    rise = rec["ss_profile_fitted"] - rec["ss_map"]
    assert rec["ss_spread"] < rise <= rec["ss_excess"] and rec["taken"] and "resolved" in rec
    s_on, s_off = _tm_ssim_env(on.envmap, truth, keep), _tm_ssim_env(off.envmap, truth, keep)
    assert s_on > s_off + 0.2, (s_off, s_on)
    # the verdict's record of the black the edge solve left (the map sky_profile=off returns) before the profile
    from objcam.solvers.plan.verdict import dark_sky_area

    grid = EnvGrid(H)
    lum = off.envmap.reshape(-1, 3)[keep].mean(axis=1)
    black = dark_sky_area(lum, grid.solid_angles().reshape(-1)[keep], np.ones(keep.size, bool))
    assert rec["dark_sky_area_solved"] == pytest.approx(black, abs=1e-6) and black > 0.05  # measured 0.12, 0.15
    _, _, old, _ = _lobe_solves(0.005, seed, 0.01, 0.0, broken=True)
    assert not old.info["edges"]["sky_profile"]["taken"]
    assert _tm_ssim_env(old.envmap, truth, keep) < s_on - 0.2


def test_a_sky_seen_in_azimuth_at_honest_noise_keeps_its_map():
    """No model error, an azimuthal step of half the sky's level at 0.5% noise: the map fits within its noise (the
    allowance is one spread) and the profile misfits by ~67 spreads, so the map is kept (a rule that allowed any
    rise would flatten the step)."""
    truth, keep, on, off = _lobe_solves(0.005, 0, 0.0, 1.0)
    rec = on.info["edges"]["sky_profile"]
    rise = rec["ss_profile_fitted"] - rec["ss_map"]
    assert rise > 5 * rec["ss_allowed"] and not rec["taken"] and on.profile is None
    np.testing.assert_array_equal(on.envmap, off.envmap)


def test_sky_floor_raises_sources_and_rims_below_their_rows_sky_and_nothing_else():
    """objcam.solvers.skyprofile.sky_floor on a 4 x 8 grid: row 1's sky at 0.2 (per channel 0.1 / 0.2 / 0.3), a rim
    texel below it raised to it channel by channel (a channel above the sky keeps its value), a source above it
    kept, an unsolved texel kept at 0, and a tied group spanning rows 1 and 2 left as it is (one value per group)."""
    import scipy.sparse as sp

    from objcam.solvers.skyprofile import sky_floor

    grid = EnvGrid(4)
    texel_index = np.arange(grid.n_texels // 2)  # rows 0 and 1 (the upper hemisphere)
    rows = texel_index // grid.width
    omega = grid.solid_angles().reshape(-1)[texel_index]
    sky = rows == 1
    rim, source, unsolved, tied = 8, 9, 10, 11
    sky[[rim, source, unsolved, tied]] = False
    x = np.zeros((texel_index.size, 3))
    x[sky] = [0.1, 0.2, 0.3]
    x[rows == 0] = 0.05  # a row without sky texels: nothing to floor to
    x[rim] = [0.0, 0.05, 0.5]
    x[source] = [5.0, 5.0, 5.0]
    x[tied] = 0.0
    # the basis: the sky of row 1 one unknown, every other texel its own, the unsolved one in none, the tied texel
    # with texel 3 of row 0 (restrict_weak's 'tie')
    groups = np.full(texel_index.size, -1)
    groups[sky] = 0
    others = np.flatnonzero(~sky & (np.arange(texel_index.size) != unsolved) & (np.arange(texel_index.size) != tied))
    groups[others] = np.arange(1, others.size + 1)
    groups[tied] = groups[3]
    inside = groups >= 0
    B = sp.csr_matrix((np.ones(inside.sum()), (np.flatnonzero(inside), groups[inside])))
    out, raised = sky_floor(x, B, sky, rows, omega)
    assert np.flatnonzero(raised).tolist() == [rim]
    np.testing.assert_allclose(out[rim], [0.1, 0.2, 0.5])
    np.testing.assert_array_equal(np.delete(out, rim, axis=0), np.delete(x, rim, axis=0))


def _sub_texel_lamp_solves(seed: int) -> tuple:
    """A lamp a quarter of a texel wide (one texel of a 4x finer grid, radiance 3,000, ~33 deg up) over a sky that
    varies with elevation, the shadows of three spheres on a plane made on the fine grid at 0.5% noise and solved on
    the 16 x 32 grid: model error of the kind the suite's lamps carry. Returns (truth area-averaged to the grid,
    kept texels, the default known solve, the same without step 5)."""
    from types import SimpleNamespace

    from objcam.envmap import resample_to_height
    from objcam.solvers.plan import known
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.targets import TargetData
    from tests.toy_scenes import sphere_shadow_toy, sphere_shadow_transport

    grid, fine, side = EnvGrid(H), EnvGrid(4 * H), 40
    tr, keep = sphere_shadow_toy(grid, side)
    kf, Af = sphere_shadow_transport(fine, side)
    theta, _ = fine.centres()
    tf = np.repeat((0.05 + 0.05 * np.cos(theta))[..., None], 3, axis=2)
    tf[13, 37] += 3000.0
    clean = Af.astype(np.float64) @ tf.reshape(-1, 3)[kf]
    y = clean + 0.005 * np.median(clean) * np.random.default_rng(seed).normal(size=clean.shape)
    d = TargetData(tr, y.reshape(side, side, 3), np.ones((side, side), bool), y, np.ones(len(y), bool))
    target = SimpleNamespace(noise_sigma=0.005, name="t")
    on = known._solve_target(target, d, SolveParams(), {})
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(known, "floor_step", lambda A, use, Y, x, *a: (x, {}))
        without = known._solve_target(target, d, SolveParams(), {})
    return resample_to_height(tf, H), keep, on, without


def _below_row_sky(sol, keep: np.ndarray) -> int:
    """Solved texels outside the profile, in a row with profile texels, whose luminance is below that row's (beyond
    float32 rounding: the envmap is float32, the row's level a mean)."""
    rows = keep // (2 * H)
    lum = sol.envmap.reshape(-1, 3)[keep].mean(axis=1)
    solved = sol.mask.reshape(-1)[keep]
    count = 0
    for r in np.unique(rows[sol.profile]):
        level = lum[sol.profile & (rows == r)].mean()
        count += int(np.sum((lum < level * (1.0 - 1e-6)) & ~sol.profile & (rows == r) & solved))
    return count


@pytest.mark.parametrize("seed", [0, 1])
def test_no_source_or_rim_is_left_darker_than_its_rows_sky(seed):
    """Step 5 (objcam.solvers.skyprofile.floor_step) under a lamp smaller than a texel: the profile is taken, and
    step 4's map leaves dark texels around the lamp (the fit's answer to its sharper shadows); the default raises
    them to their row's sky (10 and 11 texels, misfit 5.4 / 10.5 spreads up) and the map is closer to the truth
    (tonemapped SSIM 0.928 -> 0.988, 0.901 -> 0.986; with step 4's row curvature, session 37). Broken: without
    step 5 the dark rim stays and the bound fails."""
    truth, keep, on, without = _sub_texel_lamp_solves(seed)
    rec = on.info["edges"]["sky_profile"]
    assert rec["taken"] and rec["floor"]["texels_raised"] >= 5
    assert _below_row_sky(without, keep) >= 5 and _below_row_sky(on, keep) == 0
    s_on, s_without = _tm_ssim_env(on.envmap, truth, keep), _tm_ssim_env(without.envmap, truth, keep)
    assert s_on > 0.94 and s_on > s_without + 0.03, (s_without, s_on)
    peak = np.unravel_index(int(np.argmax(on.envmap[..., 1])), truth.shape[:2])
    assert abs(peak[0] - 3) <= 1 and abs(peak[1] - 9) <= 1  # the lamp's texel (fine 13, 37) within a texel


def test_row_curvature_edges_add_one_second_difference_per_column_of_three_sky_rows():
    from objcam import solvers
    from objcam.solvers.skyprofile import row_curvature_edges

    grid = EnvGrid(8)
    texel_index = np.arange(grid.width * 5)  # rows 0-4 kept
    D = solvers.difference_operator(grid, texel_index)
    sky = np.ones(texel_index.size, bool)
    sky[2 * grid.width + 3] = False  # a source texel in row 2: its column has no triple centred on rows 1, 2, 3
    E = row_curvature_edges(D, sky, texel_index, grid)
    assert (E[: D.shape[0]] != D).nnz == 0  # the first differences stay as they were
    C2 = E[D.shape[0]:]
    assert C2.shape[0] == 3 * grid.width - 3
    rows = texel_index // grid.width
    assert np.allclose(C2 @ (2.0 + 0.5 * rows), 0.0)  # a profile linear in the row costs nothing
    bump = (rows == 2).astype(float)  # one row stepping up between two: its columns' triples see it
    assert np.count_nonzero(C2 @ bump) == 3 * (grid.width - 1)
    assert np.all(np.abs(C2[:, ~sky].toarray()) == 0)  # no edge touches a texel outside the sky
    with pytest.raises(ValueError, match="one per texel"):
        row_curvature_edges(D, sky[:-1], texel_index, grid)


def _profile_rows_error(sol, truth: np.ndarray, keep: np.ndarray) -> float:
    """The largest relative error of the profile's row levels (solid-angle-free means over the row's sky)."""
    rows = keep // (2 * H)
    lum = sol.envmap.reshape(-1, 3)[keep].mean(axis=1)
    tl = truth.reshape(-1, 3)[keep].mean(axis=1)
    return max(abs(lum[sol.profile & (rows == r)].mean() / tl[sol.profile & (rows == r)].mean() - 1.0)
               for r in np.unique(rows[sol.profile]))


@pytest.mark.parametrize("seed", [0, 3])
def test_the_profile_rows_follow_a_smooth_curve_of_elevation(seed):
    """Step 4's prior adds the rows' curvature (objcam.solvers.skyprofile.row_curvature_edges): under a lamp
    smaller than a texel the first differences alone let a row two below the lamp dip to 0.85 of the truth's level
    (a band answering the lamp's model error); with the curvature the worst row is within 0.10 (measured 0.155 ->
    0.097, 0.147 -> 0.072) and the map is no worse. Broken: the first differences alone miss the bound."""
    from objcam.solvers.plan import known

    truth, keep, on, _ = _sub_texel_lamp_solves(seed)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(known, "row_curvature_edges", lambda D, sky, texel_index, grid: D)
        _, _, first_only, _ = _sub_texel_lamp_solves(seed)
    assert on.info["edges"]["sky_profile"]["taken"]
    err_on, err_off = _profile_rows_error(on, truth, keep), _profile_rows_error(first_only, truth, keep)
    assert err_on < 0.11 < err_off, (err_on, err_off)
    assert _tm_ssim_env(on.envmap, truth, keep) >= _tm_ssim_env(first_only.envmap, truth, keep) - 0.002


def test_a_profile_fitting_better_than_the_map_is_taken_only_for_one_source_over_a_sky():
    """Step 3b's test (objcam.solvers.skyprofile.profile_fit_kept): within the allowance above the map's fit it is
    kept; more than a spread below it, only where the map holds one bright blob (a lamp or the sun over a sky:
    on the hard suite 11 targets better / 3 worse, on 78 held-out targets 12 / 0; with two or more, an HDRI's sun
    and a lit façade, the map is kept: courtyard lost 0.02-0.06 SSIM as a profile). Broken: the session-31 rule
    (never below a spread) refuses the one-blob case; taking every better fit takes the two-blob case."""
    from objcam.solvers.skyprofile import profile_fit_kept

    spread, allow = 1.0, 3.0
    assert profile_fit_kept(2.5, spread, allow, blobs=2)  # within the allowance above
    assert not profile_fit_kept(3.5, spread, allow, blobs=1)  # beyond it, whatever the blobs
    assert profile_fit_kept(-0.5, spread, allow, blobs=3)  # within a spread below
    assert profile_fit_kept(-60.0, spread, allow, blobs=1)  # far better, one source over a sky: taken
    assert not profile_fit_kept(-60.0, spread, allow, blobs=2)  # far better, two bright regions: the map stays
