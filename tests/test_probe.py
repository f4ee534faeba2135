"""Chrome-ball ground truth (objcam.probe): reflection optics, ball fit, unwrap accuracy against the rendered
envmap, the perspective unwrap against the orthographic shortcut, masks, and bad inputs.

Renders are small (256 x 256, ball ~150 px, 5 cm ball at 35 cm; 64 spp), made once per module. At that size the
per-texel relative RMSE at 32 x 64 is limited by the pixel footprint (one pixel spans 1.5 deg of directions at the
ball's centre, 6 deg at 75 deg incidence, against 5.6 deg texels: bright texels leak into their neighbours) and,
near a sun, by the render's Monte Carlo noise on the few pixels that hold it (a 1.4 deg sun texel 8000x the
median: +-5-10 % of its energy at 64 spp moves the per-texel RMSE by 1-3). The bounds below are what this size
meets with margin. Measured by hand (objcam/probe/__init__.py): the target 0.05 is met at 2048 px (ball 1200 px)
by forest (0.047) and city (0.033), and by sunrise without its sun's 3 x 3 texels (0.010; 0.080 with them, the
sun's energy off by 0.3 %).
"""

from __future__ import annotations

import numpy as np
import pytest

from objcam.envmap import EnvGrid, area_downsample
from objcam.errors import InputError
from objcam.metrics import brightest_angle_deg, luminance, relative_rmse
from objcam.probe import BLIND, CAMERA, SATURATED, Reflectance, fit_ball, recover_probe
from objcam.probe.optics import CHROME_ETA, CHROME_K, fresnel_conductor, reflection_points
from objcam.probe.unwrap import ProbeEnvmap, unwrap
from objcam.synth.probe import make_bracket, probe_camera, render_probe

R = 0.025  # 5 cm ball
SPP = 64


def _sun_box(truth: np.ndarray, valid: np.ndarray):
    """Index of the 3 x 3 texels around the brightest valid texel of ``truth``."""
    lum = luminance(truth)
    r0, c0 = np.unravel_index(np.argmax(np.where(valid, lum, 0)), lum.shape)
    return slice(max(r0 - 1, 0), r0 + 2), slice(c0 - 1, c0 + 2)


@pytest.fixture(scope="module")
def scenes():
    """Two synthetic brackets (forest: off-axis ball; sunrise: sun reflected near the centre), merged."""
    out = {}
    for env, kw in (("forest", dict(offset_px=(25.0, -20.0), elevation_deg=30.0, azimuth_deg=20.0)),
                    ("sunrise", dict()),):
        r = render_probe(env, radius=R, spp=SPP, size=256, ball_px=150.0, seed=11, **kw)
        b = make_bracket(r.clean, seed=5)
        out[env] = (r, b)
    return out


@pytest.fixture(scope="module")
def fits(scenes):
    return {env: fit_ball(b.merge, r.camera, R) for env, (r, b) in scenes.items()}


# ------------------------------------------------------------------------------------------------ optics


def test_reflection_points_obey_the_mirror_law():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c, eye = np.array([0.1, -0.2, R]), np.array([0.3, 0.1, 0.25])
    rp = reflection_points(d, c, R, eye)
    v = eye - rp.point
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    refl = 2 * np.sum(rp.normal * v, axis=1, keepdims=True) * rp.normal - v
    ok = rp.converged
    assert ok.mean() > 0.99  # only directions right behind the ball fail
    assert np.abs(refl - d)[ok].max() < 1e-9
    assert np.allclose(np.linalg.norm(rp.point - c, axis=1), R)
    assert np.allclose(rp.cos_i, np.sum(rp.normal * v, axis=1))


def test_reflectance_models():
    f0 = fresnel_conductor(np.ones(()), CHROME_ETA, CHROME_K)
    assert np.all((f0 > 0.6) & (f0 < 0.72))
    cosines = np.array([1.0, 0.5, 0.0])
    for model in (Reflectance(), Reflectance(0.6, "conductor"), Reflectance(None, "conductor")):
        f = model(cosines)
        assert f.shape == (3, 3)
        assert np.allclose(f[0], model.f0()) and np.allclose(f[-1], 1.0)  # total reflection at grazing
    assert np.all(np.diff(Reflectance(0.65, "schlick")(np.linspace(1, 0, 20)), axis=0) >= 0)  # Schlick: monotonic
    assert np.allclose(Reflectance(0.6, "none")(cosines), 0.6)
    assert np.allclose(Reflectance(0.6, "conductor")(np.ones(())), 0.6)
    # chromium's exact curve dips below F0 before rising; Schlick has no dip (0.19 too high at 80 deg)
    c80 = np.cos(np.radians(80.0))
    exact = Reflectance(None, "conductor")
    assert np.all(exact(c80) < exact.f0()) and np.all(Reflectance(tuple(exact.f0()), "schlick")(c80) > exact(c80) + 0.1)
    with pytest.raises(ValueError):
        Reflectance(None, "schlick")


# ------------------------------------------------------------------------------------------------- fit


# The ball fit's bounds on these renders, between the fit's measured values and the broken fits' below
FIT_CENTRE_MM = 0.5  # measured 0.08 (forest), 0.17 mm (sunrise); broken 1.0-3.1 mm
FIT_RESIDUAL_PX = 0.55  # edge residual: measured 0.40 / 0.31 px; a diameter or a focal length 2% off 0.62-0.68
KNOWN_RESIDUAL_PX = 0.65  # at a known centre: measured 0.47 (forest); the known centre 1.5 mm off 0.85


def fit_missed(f, r, radius: float = R) -> list[str]:
    """The bounds (above) that the ball fit ``f`` of the render ``r`` (a ball of ``radius`` on the plane) misses."""
    err_mm = 1e3 * np.linalg.norm(f.centre_world - r.centre)
    print("fit_ball: centre", err_mm, "mm, residual", f.residual_px, "px, inliers", f.inlier_fraction, f.warnings)
    missed = [] if err_mm < FIT_CENTRE_MM else ["centre"]
    missed += [] if f.centre_world[2] == pytest.approx(radius) else ["height"]
    missed += [] if f.residual_px < FIT_RESIDUAL_PX else ["residual"]
    missed += [] if f.inlier_fraction > 0.9 else ["inliers"]
    return missed + (["warnings"] if f.warnings else [])


@pytest.mark.parametrize("env", ["forest", "sunrise"])
def test_fit_ball_on_the_plane(scenes, fits, env):
    """Broken variants (test_a_broken_fit_misses_the_bounds): the ball's diameter or the focal length 2% off, the
    principal point 3 px off, a known centre 1.5 mm off."""
    r, _ = scenes[env]
    assert fit_missed(fits[env], r) == []


# broken fits of the forest render: (fit_ball's wrong input, the bounds they must miss at least one of; measured)
BROKEN_FITS = {
    "diameter 2% too large": ("centre", "height", "residual"),  # 2.0 mm, z 25.5 mm, 0.65 px
    "focal length 2% too long": ("centre", "residual"),  # 1.2 mm, 0.65 px
    "principal point 3 px off": ("centre",),  # 1.0 mm (residual 0.40: the silhouette still fits)
    "known centre 1.5 mm off": ("centre", "residual", "inliers", "warnings"),  # 1.5 mm, 0.85 px, 0.87, warned
}


@pytest.mark.parametrize("broken", list(BROKEN_FITS))
def test_a_broken_fit_misses_the_bounds(scenes, broken):
    """A test of the test (tests/broken.py): fit_ball on the same render with a wrong ball size, camera or known
    centre misses the bounds of test_fit_ball_on_the_plane."""
    r, b = scenes["forest"]
    cam, radius, known = r.camera, R, None
    if broken.startswith("diameter"):
        radius = 1.02 * R
    elif broken.startswith("focal"):
        cam = cam.model_copy(update=dict(fx=1.02 * cam.fx, fy=1.02 * cam.fy))
    elif broken.startswith("principal"):
        cam = cam.model_copy(update=dict(cx=cam.cx + 3.0))
    else:
        known = r.centre + [1.5e-3, 0.0, 0.0]
    missed = fit_missed(fit_ball(b.merge, cam, radius, known_centre=known), r, radius)
    assert set(BROKEN_FITS[broken]) & set(missed), (broken, missed)


def test_fit_ball_known_and_hinted(scenes):
    """Broken variants, asserted below: a known centre 1.5 mm off (residual, offset), a free fit with a ball 5%
    too large (depth) or a principal point 3 px off (projection)."""
    r, b = scenes["forest"]
    known = fit_ball(b.hdr, r.camera, R, known_centre=r.centre)
    assert np.array_equal(known.centre_world, r.centre) and known.mode == "known"
    assert known.residual_px < KNOWN_RESIDUAL_PX
    # checked against the photo: a fit at its height puts the ball next to it ...
    assert known.fitted_offset_mm < 0.5 and not known.warnings  # measured 0.10 mm
    # ... and a known centre 1.5 mm off (a misplaced ball, a wrong board pose) is warned about, with the offset
    off = fit_ball(b.hdr, r.camera, R, known_centre=r.centre + [1.5e-3, 0.0, 0.0])
    assert np.array_equal(off.centre_world, r.centre + [1.5e-3, 0.0, 0.0])  # still used as given
    assert off.fitted_offset_mm == pytest.approx(1.5, abs=0.5)  # measured 1.42
    assert any("mm from the known centre" in w for w in off.warnings)
    # (a test of the test: the misplaced centre misses both bounds the right one meets)
    assert off.residual_px >= KNOWN_RESIDUAL_PX and off.fitted_offset_mm >= 0.5
    u, v = r.camera.project(r.centre)

    def free(cam=r.camera, radius=R):
        f = fit_ball(b.hdr, cam, radius, rests_on_plane=False, approx_px=(u + 2, v - 2, 73.0))
        return 1e3 * np.linalg.norm(f.centre_world - r.centre), np.linalg.norm(r.camera.project(f.centre_world) - (u, v))

    # no plane: the depth hangs on the apparent size (sub-pixel edge bias -> millimetres): measured 1.2 mm, 0.16 px
    # (2.4 mm, 0.6 px in an earlier session); a ball 3% too large 9.3 mm
    mm, px = free()
    assert mm < 5.0 and px < 1.0
    # a test of the test: a ball 5% too large (16 mm) and a principal point 3 px off (2.8 px) miss them
    assert free(radius=1.05 * R)[0] >= 5.0
    assert free(cam=r.camera.model_copy(update=dict(cx=r.camera.cx + 3.0)))[1] >= 1.0


# ------------------------------------------------------------------------------------------------ unwrap


@pytest.mark.parametrize("env", ["forest", "sunrise"])
def test_unwrap_matches_the_envmap(scenes, fits, env):
    r, b = scenes[env]
    res = recover_probe(b.merge, r.camera, R, reflectance=r.reflectance, solve_height=32)
    assert np.linalg.norm(res.fit.centre_world - fits[env].centre_world) < 1e-9
    truth = area_downsample(r.envmap.astype(np.float64), 32)
    est, valid = res.envmap / b.scale, res.valid  # merge units -> scene radiance
    w = EnvGrid(32).solid_angles()
    assert (w * valid).sum() / w.sum() > 0.85  # blind spot and camera cone are ~4 % of the sphere
    # forest's brightest patch is two texels (the second at 59 % of the first): the metric's 50 %-region either
    # takes both (0.2 deg) or, when blur leaves the estimate's second texel under half, one (1.97 deg)
    assert brightest_angle_deg(est, truth, valid) < 2.0
    box = _sun_box(truth, valid)
    rest = valid.copy()
    rest[box] = False
    e_sun = (luminance(est) * w)[box].sum() / (luminance(truth) * w)[box].sum()
    assert abs(e_sun - 1) < 0.2  # the sun's energy: render MC noise, measured 0.86-1.10 over seeds
    assert relative_rmse(est, truth, rest) < 0.2  # measured 0.15 (forest), 0.06 (sunrise)
    if env == "forest":  # whole map; sunrise's (2.5-3.7) is the MC noise on its sun texel, 1000x the mean
        assert relative_rmse(est, truth, valid) < 0.5  # measured 0.33 (0.46 with another seed)
    # a test of the test (tests/broken.py): the estimate turned 90 degrees and the truth's flat sky miss the bounds
    # (measured: turned 82 / 89 deg and 3.4 / 52 away from the sun; flat 1.8 / 3.0)
    from tests.broken import rotated, truth_constant

    turned, flat = rotated(est, valid, 90.0), truth_constant(truth, valid)
    assert brightest_angle_deg(turned, truth, valid) >= 2.0 and relative_rmse(turned, truth, rest) >= 0.2
    assert relative_rmse(flat, truth, rest) >= 0.2


def test_perspective_beats_orthographic_close_up():
    """A ball 12 cm away: the shortcut that treats the camera as infinitely far misplaces directions by degrees."""
    c = np.array([0.0, 0.0, R])
    r = render_probe("forest", radius=R, distance=0.12, size=192, ball_px=150.0, spp=16, seed=2)
    truth = area_downsample(r.envmap.astype(np.float64), 32)
    errs = {}
    for proj in ("perspective", "orthographic"):
        p = unwrap(r.clean, r.camera, c, R, reflectance=r.reflectance, projection=proj)
        est, valid, _ = p.downsample(32)
        errs[proj] = relative_rmse(est, truth, valid)
    assert errs["perspective"] < 0.5 * errs["orthographic"], errs  # measured 0.33 vs 1.30


def test_masks_and_saturation(scenes):
    r, _ = scenes["sunrise"]
    b = make_bracket(r.clean, n_frames=3, seed=1)  # no short frames: the sun clips in all of them
    assert b.merge.n_invalid > 0
    res = recover_probe(b.merge, r.camera, R, reflectance=r.reflectance, solve_height=32)
    p = res.probe
    assert res.lower_bound and p.saturated.any()
    truth = area_downsample(r.envmap.astype(np.float64), 32)
    box = _sun_box(truth, np.ones(truth.shape[:2], bool))
    sun = np.unravel_index(np.argmax(luminance(truth)), truth.shape[:2])
    assert res.saturated[sun] and not res.valid[sun]
    assert luminance(res.envmap / b.scale)[sun] < 0.5 * luminance(truth)[sun]  # a lower bound
    assert res.valid[box].sum() < 9
    # blind spot: straight behind the ball; camera cone: straight towards the camera
    d = EnvGrid(p.flags.shape[0]).directions()
    to_cam = r.camera.centre - r.centre
    to_cam /= np.linalg.norm(to_cam)
    assert np.all(p.flags[d @ to_cam > np.cos(np.radians(9))] & CAMERA)
    assert np.all(p.flags[d @ -to_cam > np.cos(np.radians(19))] & BLIND)
    assert np.all(p.envmap[(p.flags & (BLIND | CAMERA)) != 0] == 0)


def test_downsample_validity_rule():
    """A coarse texel is valid when >= half its solid angle is valid and none of it is saturated; its value
    averages the observed (valid or saturated) fine texels by solid angle."""
    h = 8
    flags = np.zeros((h, 2 * h), np.uint8)
    env = np.ones((h, 2 * h, 3), np.float32)
    flags[0:4, 0:1] = BLIND  # coarse (0, 0): a quarter of its solid angle blind -> valid
    flags[4:6, 4:8] = BLIND  # coarse (1, 1): its two rows nearer the equator (70 % of its solid angle) -> invalid
    flags[0:1, 12:13] = SATURATED  # coarse (0, 3): one saturated fine texel -> saturated, invalid
    env[0:1, 12:13] = 50.0
    p = ProbeEnvmap(env, flags, np.ones((h, 2 * h), np.float32), "perspective")
    e, valid, sat = p.downsample(2)
    w = EnvGrid(h).solid_angles()
    assert valid[0, 0] and not valid[1, 1] and (w[4:6, 4:8].sum() / w[4:8, 4:8].sum()) > 0.5
    assert sat[0, 3] and not valid[0, 3] and sat.sum() == 1
    expect = (w[0:4, 12:16].sum() + 49.0 * w[0, 12]) / w[0:4, 12:16].sum()
    assert e[0, 3, 0] == pytest.approx(expect, rel=1e-6)
    assert np.allclose(e[~sat], 1.0) and valid.sum() == 2 * 2 * 2 - 2


# -------------------------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def bad_renders():
    c = np.array([0.0, 0.0, R])
    cam = probe_camera(c, R)
    out = {"none": render_probe("forest", centre=(5.0, 5.0, R), camera=cam, spp=8).clean}
    cam2 = probe_camera(c, R, ball_px=70.0)
    out["two"] = render_probe("forest", camera=cam2, spp=8, extra_balls=[((0.0, 0.05, R), R)]).clean
    cam3 = probe_camera(c, R, offset_px=(100.0, 0.0))
    out["cut"] = render_probe("forest", camera=cam3, spp=8).clean
    return out, {"none": cam, "two": cam2, "cut": cam3}


@pytest.mark.parametrize("case, message", [("none", "no chrome ball"), ("two", "two ball-like"),
                                           ("cut", "cut by the image edge")])
def test_bad_ball_images(bad_renders, case, message):
    imgs, cams = bad_renders
    with pytest.raises(InputError, match=message) as e:
        fit_ball(imgs[case], cams[case], R, source="probe/ball.exr")
    assert "probe/ball.exr" in str(e.value) and "fix:" in str(e.value)


@pytest.mark.parametrize("gain, message, frame", [(1e4, "saturated in every frame", 0),
                                                  (1e-6, "no usable signal", -1)])
def test_bad_brackets(scenes, gain, message, frame):
    r, b = scenes["forest"]
    bad = make_bracket(r.clean, times=[t * gain for t in b.times[:3]], seed=3)
    with pytest.raises(InputError, match=message) as e:
        recover_probe(bad.merge, r.camera, R)
    assert bad.merge.paths[frame].name in str(e.value)
