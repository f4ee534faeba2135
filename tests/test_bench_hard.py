"""The hard-case suite's own Mitsuba scene (bench/hard): its envmap and camera orientation against geometry, its
lighting, and a tiny case written as a capture that ``objcam run`` accepts and solves."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bench.hard.lighting import Lighting, add_disc, make_envmap
from bench.hard.objects import box, write_ply
from bench.hard.scene import overhead_camera, render
from bench.hard.score import band_energy_ratios, source_contrast
from objcam.camera import Camera


def _lamp_only(elev: float, az: float, h: int = 64) -> np.ndarray:
    env = np.full((h, 2 * h, 3), 1e-4)
    add_disc(env, elev, az, 4.0, (1.0, 1.0, 1.0))
    return env


POST = np.array([0.02, 0.01])  # the post's centre on the plane (m), off the origin so that a mirror shows


def _post_errors(img: np.ndarray, cam: Camera, az: float) -> tuple[float, float]:
    """(pixels from the post's top, as found in the image ``img`` (H, W, 3), to where ``cam`` projects it; degrees
    between the shadow's offset from the post, found in the image and taken to z = 0 through ``cam``'s rays, and
    the direction away from a lamp at azimuth ``az``)."""
    lum = img.mean(axis=-1)
    lit = float(np.median(lum))
    # the post's top: the brightest pixels (albedo 0.9 against the plane's 0.3)
    top = np.argwhere(lum > 2.0 * lit)
    top_px = float(np.linalg.norm(top.mean(axis=0)[::-1] - cam.project(np.array([*POST, 0.04]))))
    # the shadow: plane pixels much darker than the lit plane; onto z = 0 through the camera's rays
    rows, cols = np.nonzero(lum < 0.3 * lit)
    o, d = cam.rays(cols.astype(float), rows.astype(float))
    hit = o + d * (-o[:, 2] / d[:, 2])[:, None]
    away = hit[:, :2].mean(axis=0) - POST
    want = -np.array([math.cos(math.radians(az)), math.sin(math.radians(az))])
    return top_px, math.degrees(math.acos(np.clip(np.dot(away, want) / np.linalg.norm(away), -1, 1)))


def _post_ok(top_px: float, ang: float) -> bool:
    return top_px < 1.5 and ang < 5.0


@pytest.mark.parametrize("az", [30.0, 200.0])
def test_a_lamps_shadow_points_away_from_it(tmp_path, az):
    """A post off the origin, seen from straight above, under one lamp at 45 degrees elevation: the shadow (found in
    the image and taken to the plane through the contract's camera) lies on the side away from the lamp, and the
    post's top projects where the camera says. Broken variants, asserted below: an envmap mirrored in azimuth
    (rendered again, 16 spp at 48 x 48) and a mirrored camera (the image flipped left-right) each miss a bound."""
    v, f = box((*(POST - 0.004), 0.0), (*(POST + 0.004), 0.04))
    mesh = tmp_path / "post.ply"
    write_ply(mesh, v, f)
    cam_json = overhead_camera(48, 0.3)
    cam = Camera.model_validate(cam_json)
    img, _ = render(mesh, cam_json, _lamp_only(45.0, az), 0.9, 0.3, spp=16, seed=0, max_depth=2)
    errs = _post_errors(img, cam, az)
    assert _post_ok(*errs), errs  # measured 0.32 / 0.22 px, 2.25 / 2.21 degrees (az 30 / 200)
    # measured: the mirrored envmap's shadow 60 / 41 degrees off; the mirrored camera's top 6.7 / 6.2 px off
    mirrored_env, _ = render(mesh, cam_json, _lamp_only(45.0, az)[:, ::-1], 0.9, 0.3, spp=16, seed=0, max_depth=2)
    for broken in (mirrored_env, img[:, ::-1]):
        errs = _post_errors(broken, cam, az)
        assert not _post_ok(*errs), errs


def _lamp_errors(env: np.ndarray, elev: float, az: float) -> tuple[float, float]:
    """(elevation, azimuth) errors in degrees of the brightest texel of ``env`` (H, 2H, 3) against a lamp at
    (``elev``, ``az``) degrees."""
    h = env.shape[0]
    r, c = np.unravel_index(int(np.argmax(env[..., 0])), env.shape[:2])
    found_az = 360.0 * (c + 0.5) / (2 * h)
    return 90.0 - 180.0 * (r + 0.5) / h - elev, (found_az - az + 180.0) % 360.0 - 180.0


def test_lighting_families_hold_what_they_say():
    """Broken variants, asserted below (each misses the lamp's 0.5 degree bound): the map turned the other way
    (-137 degrees: azimuth 86 degrees off), upside down (elevation 20 degrees off), and left unturned (137 off)."""
    env, rot = make_envmap(Lighting("lamp", "lamp10", 10.0), 137.0)
    assert env.shape == (256, 512, 3) and rot == 137.0
    errs = _lamp_errors(env, 10.0, 30.0 + 137.0)  # the lamp at 30 + rotation degrees
    # measured 0.20 / 0.01 degree (elevation / azimuth: the brightest texel's centre, 0.70 degree texels, so up to
    # 0.35 from quantisation alone); bound 0.5 degree (was 1.5, which passed a lamp a texel or two off)
    assert max(map(abs, errs)) < 0.5, errs
    for broken in (np.roll(env, -int(round(2 * 137.0 / 360.0 * env.shape[1])), axis=1), env[::-1],
                   make_envmap(Lighting("lamp", "lamp10", 10.0), 0.0)[0]):
        errs = _lamp_errors(broken, 10.0, 30.0 + 137.0)
        assert not max(map(abs, errs)) < 0.5, errs
    small = env.reshape(32, 8, 64, 8, 3).mean(axis=(1, 3))  # (equal-weight mean is enough for a contrast)
    assert source_contrast(small) > 100  # one lamp on a dim sky
    env2, rot2 = make_envmap(Lighting("hdri", "forest", hdri="forest"), 137.0)
    assert abs(rot2 - 137.0) < 0.36  # whole columns of 0.7 degrees
    # the band energies of a map against itself are 1, and double where it is doubled
    est = small.copy()
    est[:5] *= 2  # rows 0-4: elevation 62-90 degrees
    assert band_energy_ratios(small, small) == pytest.approx([1, 1, 1, 1])
    assert band_energy_ratios(est, small)[3] > 1.5 and band_energy_ratios(est, small)[0] == pytest.approx(1)


def test_a_tiny_case_is_a_capture_objcam_runs(tmp_path):
    """The suite's capture writer on one 32 x 32 render at low spp: the scene stage accepts it, evaluate scores both
    noise levels with their baselines, and the lamp is recovered near where it is (an end-to-end orientation
    check through objcam's own solve)."""
    from tests.hard_capture import tiny_hard_capture

    cap, rows = tiny_hard_capture(tmp_path, 60.0)
    toml = (cap / "capture.toml").read_text()
    assert 'object = "object.ply"' in toml and toml.count("[[targets]]") == 2
    assert json.loads((cap / "targets" / "lamp30_r0_n2.json").read_text())["width"] == 32
    by = {r["target"]: r for r in rows}
    assert set(by) == {"lamp30_r0_n0.5", "lamp30_r0_n2"}
    for r in rows:
        if r["negative_pixels"]:
            assert r["status"] == "refused"  # today's scene stage; never clipped
            continue
        assert r["status"] == "ok", r["error"]
        # the lamp, 30 degrees up at azimuth 30: measured 0.7-1.0 degrees off (one solve texel is 5.6)
        assert r["brightest_angle_deg"] < 6.0, r
        # a test of the test: the truth's flat and row-mean maps, scored on the same mask, miss it (measured 59 deg)
        assert min(r["baselines"][b]["brightest_angle_deg"] for b in ("constant", "row_mean")) >= 6.0, r
        assert set(r["baselines"]) == {"constant", "row_mean"} and len(r["band_energy"]) == 4


def _row(target, noise, ssim, rm_ssim=0.5, bands=(1.0, 1.0, 1.0, 1.0), angle=1.0, contrast=10.0, status="ok"):
    return {"target": target, "noise": noise, "status": status, "error": "" if status == "ok" else "refused here",
            "ssim": ssim, "band_energy": list(bands), "brightest_angle_deg": angle, "source_contrast": contrast,
            "beats_row_mean": {"ssim": ssim > rm_ssim, "tonemapped_rmse": ssim > rm_ssim}}


def test_the_blocks_targets_say_met_missed_and_not_measured():
    from bench.hard.report import targets

    rows = [_row("a", 0.02, 0.72), _row("b", 0.02, 0.71), _row("c", 0.02, 0.40, bands=(1.0, 2.5, 1.0, 1.0)),
            _row("d", 0.005, 0.80), _row("e", 0.005, 0.79, angle=9.0), _row("f", 0.005, 0.1, status="refused")]
    text = "\n".join(targets(rows))
    assert "**missed**: SSIM at 2% noise: median 0.710 (>= 0.7), worst 0.400 (>= 0.45) (3 solved)" in text
    # the median is met on the solved ones, but a refused target means the level was not fully measured
    assert "**missed**: SSIM at 0.5% noise: median 0.795 (>= 0.78) (2 solved, 1 not solved: not measured)" in text
    assert "[0.67, 1.5] of the truth's energy in >= 90% of targets: 80%" in text
    assert "**missed**: every band within [0.5, 2] in all targets: 80%" in text
    assert "within 5.6 deg in >= 95% of the 5 targets whose brightest source is >= 3x the next: 80%" in text
    assert "met: beats the row-mean oracle in >= 80% of targets in SSIM and in tonemapped RMSE (issue 28): 80% and " \
           "80%" in text
    rows[0]["beats_row_mean"]["tonemapped_rmse"] = False  # one metric short: missed
    assert "**missed**: beats the row-mean oracle in >= 80% of targets in SSIM and in tonemapped RMSE (issue 28): " \
           "80% and 60%" in "\n".join(targets(rows))
    assert "1 of 6 targets refused: refused here (f)" in text


def test_the_verdict_line_names_targets_where_ssim_cannot_tell_a_map_from_a_flat_one():
    """A red grade on a target whose truth's constant map already scores SSIM >= 0.99 (a room's flat walls at the
    tonemap's white) is counted, and named apart; a target whose flat map scores less is not set apart."""
    from bench.hard.report import targets

    def graded(target, ssim, grade, const):
        r = _row(target, 0.02, ssim)
        r.update(verdict={"grade": grade}, baselines={"constant": {"ssim": const}, "row_mean": {"ssim": 0.5}})
        return r

    rows = [graded("room", 1.0, "red", 0.998), graded("lamp", 0.9, "red", 0.95), graded("sky", 0.8, "green", 0.3)]
    line = next(x for x in targets(rows) if "SSIM >= 0.7 graded red" in x)
    assert line.startswith("- **missed**: no target with SSIM >= 0.7 graded red: 2 of 3 (room, lamp)"), line
    assert line.endswith("the truth's constant map scores >= 0.99: room), so 1 of 2 otherwise"), line


def test_the_beats_line_names_targets_whose_row_mean_map_no_map_can_beat():
    """A target whose row-mean map scores SSIM 1 (a dark room's truth white over the whole sky once tonemapped) is
    named beside the beats-row-mean share, with the share that is then the most any solve can reach; a row-mean
    map scoring just below 1 is not set apart."""
    from bench.hard.report import targets

    def scored(target, ssim, rm):
        r = _row(target, 0.02, ssim, rm_ssim=rm)
        r["baselines"] = {"constant": {"ssim": 0.5}, "row_mean": {"ssim": rm}}
        return r

    rows = [scored("room", 0.999, 1.0 + 4e-14), scored("lamp", 0.97, 0.98), scored("sky", 0.8, 0.5),
            scored("sun", 0.99, 1.0 - 1e-6)]
    line = next(x for x in targets(rows) if "beats the row-mean oracle" in x)
    assert line.startswith("- **missed**: beats the row-mean oracle in >= 80% of targets in SSIM and in tonemapped "
                           "RMSE (issue 28): 25% and 25%"), line
    assert line.endswith("no map can beat it, so at most 75%): room"), line
    plain = next(x for x in targets(rows[1:]) if "beats the row-mean oracle" in x)
    assert "no map can beat it" not in plain, plain


def _plane_irradiance_as_emitted(bitmap: np.ndarray, n_t: int = 2048, n_p: int = 1024) -> float:
    """Luminance irradiance on an up-facing plane, int L cos(theta) dw over the upper hemisphere, with L Mitsuba's
    envmap loaded as bench/hard/scene.py loads ``bitmap`` (midpoint rule)."""
    import drjit as dr
    import mitsuba as mi

    from bench.hard.scene import envmap_to_world

    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb")
    em = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(bitmap[:, ::-1])),
                       "to_world": mi.ScalarTransform4f(envmap_to_world().tolist())})
    theta = (np.arange(n_t) + 0.5) * (np.pi / 2) / n_t
    phi = (np.arange(n_p) + 0.5) * 2 * np.pi / n_p
    T, P = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
    si.wi = mi.Vector3f(*(-d.T).astype(np.float32))  # eval looks up the direction -wi
    lum = np.asarray(em.eval(si), np.float64).T @ np.array([0.2126, 0.7152, 0.0722])
    return float((lum * (np.cos(T) * np.sin(T)).ravel()).sum() * (np.pi / 2 / n_t) * (2 * np.pi / n_p))


def test_the_renderer_emits_the_truths_light():
    """The suite's targets are renders of their truth: a lamp 5 deg from the zenith, as the renderer hands it to
    Mitsuba (contract_bitmap), lights the plane as the truth's box texels say (measured 0.002% off). Handed
    Mitsuba the rows as they are (the suite's renders before session 21), the sky is stretched towards the poles
    and the plane got 4.8% less: what the lamp-85 targets showed against A x_truth (0.953 on three captures)."""
    from bench.hard.scene import contract_bitmap

    env, _ = make_envmap(Lighting("lamp", "lamp85", 85.0), 0.0)
    h = env.shape[0]
    t0 = np.pi * np.arange(h) / h
    cos_w = (np.sin(t0 + np.pi / h) ** 2 - np.sin(t0) ** 2) / 2 * (np.pi / h)  # int cos sin dtheta per row
    cos_w[h // 2:] = 0.0
    truth = float(((env @ np.array([0.2126, 0.7152, 0.0722])) * cos_w[:, None]).sum())
    assert _plane_irradiance_as_emitted(contract_bitmap(env)) / truth == pytest.approx(1.0, abs=0.005)
    assert _plane_irradiance_as_emitted(env.astype(np.float32)) / truth < 0.97  # the rows as they are


def test_decompose_says_whether_the_sky_or_the_source_loses_the_ssim():
    """bench.hard.decompose: a map whose sky is noisy and source exact loses nothing when the sky is fixed; one
    whose source is lost (a dark hole where it was) and sky exact loses nothing when the source's neighbourhood
    is fixed."""
    import numpy as np

    from bench.hard.decompose import source_neighbourhood, split_scores

    h = 16
    rows = np.linspace(0.05, 0.03, h)[:, None, None] * np.ones((h, 2 * h, 3))
    truth = rows.copy()
    truth[h // 2:] = 0.01
    truth[4, 10] = 500.0  # a lamp
    mask = np.zeros((h, 2 * h), bool)
    mask[: h // 2] = True
    near = source_neighbourhood(truth)
    assert near[4, 10] and near[2, 12] and not near[4, 13] and near.sum() == 25
    rng = np.random.default_rng(0)
    noisy_sky = truth * np.exp(rng.normal(0, 0.5, truth.shape[:2]))[..., None]
    noisy_sky[near] = truth[near]
    s = split_scores(noisy_sky, truth, mask)
    assert s["ssim"] < 0.8 and s["sky_fixed"] == pytest.approx(1.0) and s["sources_fixed"] == pytest.approx(s["ssim"])
    lost = truth.copy()
    lost[3:6, 9:12] = 0.0  # a hole where the lamp was
    s = split_scores(lost, truth, mask)
    assert s["ssim"] < 0.95 and s["sources_fixed"] == pytest.approx(1.0) and s["sky_fixed"] == pytest.approx(s["ssim"])


def test_compare_summarises_families_and_pairs_targets():
    """bench.hard.compare: per-family medians, row-mean wins, the brightest and band shares, and the paired
    change on the targets both runs solved."""
    from bench.hard.compare import family_summary, paired

    def row(target, fam, ssim, rm, bright, bands, noise=0.02):
        return {"target": target, "geometry": "g", "family": fam, "ssim": ssim, "noise": noise,
                "baselines": {"row_mean": {"ssim": rm}}, "tonemapped_rmse": 1 - ssim,
                "brightest_angle_deg": bright, "band_energy": bands}

    base = [row("a", "lamp", 0.6, 0.9, 1.0, [1.0, 1.2, None, 0.9]),
            row("b", "lamp", 0.8, 0.7, 9.0, [1.0, 2.0, 1.0, 1.0]),
            row("c", "hdri", 0.7, 0.4, 0.5, [0.7, 1.0, 1.0, 1.4])]
    s = family_summary(base)
    assert s["all"]["n"] == 3 and s["all"]["ssim_median"] == pytest.approx(0.7)
    assert s["lamp"]["beats_row_mean"] == 1 and s["all"]["beats_row_mean"] == 2
    assert s["lamp"]["brightest_within_texel"] == pytest.approx(0.5)
    # a: a band with no truth energy (None) counts as out of range, as in the suite's block; b: 2.0; c: in range
    assert s["all"]["bands_in_range"] == pytest.approx(1 / 3)
    other = [row("a", "lamp", 0.65, 0.9, 1.0, [1.0] * 4), row("b", "lamp", 0.8, 0.7, 1.0, [1.0] * 4),
             row("d", "lamp", 0.1, 0.9, 1.0, [1.0] * 4)]  # d: not in the base, not paired
    p = paired(base, other)
    assert p["n"] == 2 and p["better"] == 1 and p["worse"] == 0 and p["max"] == pytest.approx(0.05)


def test_render_noise_is_the_median_pixels_not_the_fireflies():
    """capture.toml's noise_sigma takes the render's noise at the median pixel (bench.hard.scene.median_pixel_noise):
    a hundred fireflies on a bright object leave it at the median pixel's 1%, where the whole image's deviation
    (RENDER_VERSION v3's measure, the broken setting) reads several times that."""
    from bench.hard.scene import median_pixel_noise

    rng = np.random.default_rng(0)
    img = np.full((64, 64, 3), 1.0)
    img[:16] = 8.0  # a bright object over a quarter of the image
    half = 0.01 * rng.normal(size=img.shape)  # 1% of the median pixel, everywhere
    half[:16] *= 4.0  # more noise on the object, as a path tracer's
    half[rng.integers(0, 16, 100), rng.integers(0, 64, 100)] += 5.0  # fireflies
    got = median_pixel_noise(img, half)
    assert got == pytest.approx(0.01, rel=0.05)
    assert float(np.std(half)) > 5 * got  # the v3 measure


def test_held_out_rotations_keep_the_design_and_turn_every_lighting():
    """`--rotations` (a held-out check of a rule chosen on the suite): the same lightings on the same geometries,
    each at an angle the suite never used; a count other than the design's is refused."""
    from bench.hard.design import ROTATIONS, cases

    suite, held = cases(), cases(rotations=(60.0, 200.0, 310.0))
    assert len(held) == len(suite)
    assert all(a.light == b.light and a.geometry == b.geometry for a, b in zip(suite, held))
    assert {b.rotation_deg for b in held} == {60.0, 200.0, 310.0}
    assert not {b.rotation_deg for b in held} & set(ROTATIONS)
    with pytest.raises(ValueError, match="one per geometry slot"):
        cases(rotations=(60.0, 200.0))


def test_the_held_out_design_shares_nothing_with_the_suite_but_its_families():
    """`--design held-out`: every object, camera elevation, albedo pair, rotation and lighting other than the
    suite's (so no rule chosen on the suite was chosen on it), crossed the same way: each lighting's three
    rotations meet all three objects and all three elevations."""
    from bench.hard.design import HELD_OUT, SUITE, cases

    suite, held = cases(), cases(design=HELD_OUT)
    assert len(held) == 3 * len(HELD_OUT.lightings) == 42
    geos = lambda cs, f: {f(c) for c in cs}  # noqa: E731
    for f in (lambda c: c.geometry.object, lambda c: c.geometry.elevation_deg, lambda c: c.rotation_deg,
              lambda c: (c.geometry.albedo_object, c.geometry.albedo_support), lambda c: c.light.name):
        assert not geos(suite, f) & geos(held, f)
    assert {c.light.family for c in held} - {c.light.family for c in suite} == {"overcast"}
    for light in HELD_OUT.lightings:
        mine = [c for c in held if c.light == light]
        assert {c.geometry.object for c in mine} == set(HELD_OUT.objects)
        assert {c.geometry.elevation_deg for c in mine} == set(HELD_OUT.elevations)
    assert SUITE.rotations == (0.0, 137.0, 251.0)


@pytest.mark.parametrize("name", ["knot", "mug", "sphere"])
def test_held_out_objects_rest_on_the_plane_with_outward_faces(name):
    """The generated objects: 8 cm across or tall, resting on z = 0, faces wound outward (the signed volume of
    the closed knot and sphere is their solid's; the mug's handle is an open tube whose ends hide in the wall).
    A mesh wound inward, the test of the test, has the opposite volume."""
    from bench.hard.objects import make_object

    v, f = make_object(name)
    assert np.isfinite(v).all() and v[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert np.ptp(v, axis=0).max() == pytest.approx(0.08, rel=0.01)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
    expect = {"sphere": 4 / 3 * math.pi * 0.04**3,  # the tube: length x cross-section
              "knot": float(np.linalg.norm(np.diff(v[::16][: len(v) // 16], axis=0, append=v[:1]), axis=1).sum())
              * math.pi * 0.004**2,
              "mug": math.pi * (0.024**2 * 0.08 - 0.020**2 * 0.074)}[name]
    assert vol == pytest.approx(expect, rel=0.1 if name != "knot" else 0.25)
    a, b, c = v[f[:, 0]], v[f[:, 2]], v[f[:, 1]]
    assert float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0 < 0


def test_held_out_lightings_hold_what_they_say():
    """The held-out lightings the suite has no twin of: the overcast sky falls from the zenith to a third of it at
    the horizon whatever the rotation; the tall window sits where its knobs put it; the unbundled HDRIs load,
    non-negative, turned by the rotation."""
    from bench.hard.lighting import held_out_lightings

    light = {x.name: x for x in held_out_lightings()}
    env, _ = make_envmap(light["overcast"], 60.0)
    assert np.array_equal(env, make_envmap(light["overcast"], 200.0)[0])
    assert env[0, :, 0].mean() == pytest.approx(1.0, abs=0.01)
    assert env[127, :, 0].mean() == pytest.approx(1 / 3, abs=0.01)
    win, _ = make_envmap(light["window2"], 0.0)
    lum = win[..., 1]
    rows, cols = np.nonzero(lum > 1.0)
    elev = 90.0 - 180.0 * (rows + 0.5) / 256
    az = 360.0 * (cols + 0.5) / 512
    assert 10 <= elev.min() < 11 and 59 < elev.max() <= 60 and 68 < az.min() < 69 and 91 < az.max() < 92
    for name in ("interior", "night", "studio"):
        a, rot = make_envmap(light[name], 60.0)
        b, _ = make_envmap(light[name], 0.0)
        assert a.shape == (256, 512, 3) and a.min() >= 0 and np.array_equal(a, np.roll(b, int(rot / 360 * 512), 1))
