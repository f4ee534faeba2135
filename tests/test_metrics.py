"""Envmap / image metrics on hand-made maps with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from objcam.envmap import EnvGrid, rotate_z, spherical_to_direction
from objcam.metrics import (
    angle_deg,
    best_scale,
    envmap_metrics,
    image_relative_rmse,
    pad_sphere,
    brightest_angle_deg,
    brightest_direction,
    relative_rmse,
    ssim,
    ssim_map,
    tonemap,
    tonemap_scale,
)


def sky(h=16, seed=0):
    grid = EnvGrid(h)
    theta, phi = grid.centres()
    base = 0.5 + 0.5 * np.cos(theta) + 0.2 * np.sin(2 * phi) * np.sin(theta)
    return np.stack([base, 0.8 * base, 1.1 * base], -1)


def blob(h, theta0, phi0, width_deg=6.0, peak=50.0):
    grid = EnvGrid(h)
    d0 = spherical_to_direction(np.float64(theta0), np.float64(phi0))
    ang = np.arccos(np.clip(grid.directions() @ d0, -1, 1))
    v = peak * np.exp(-0.5 * (ang / np.radians(width_deg)) ** 2)
    return np.repeat(v[..., None], 3, axis=-1)


def upper_mask(h):
    m = np.zeros((h, 2 * h), bool)
    m[: h // 2] = True
    return m


# ------------------------------------------------------------------------------------------------ relative RMSE


def test_relative_rmse_known_values():
    h = 8
    truth = np.full((h, 2 * h, 3), 2.0)
    est = truth + 0.2
    mask = upper_mask(h)
    assert relative_rmse(est, truth, mask) == pytest.approx(0.1)
    # Error only in row 0 (the zenith row): plain vs solid-angle weighted.
    est = truth.copy()
    est[0] += 1.0
    rows = h // 2
    assert relative_rmse(est, truth, mask) == pytest.approx(np.sqrt(1.0 / rows) / 2.0)
    omega = EnvGrid(h).solid_angles()
    frac = omega[0].sum() / omega[mask].sum()
    assert relative_rmse(est, truth, mask, solid_angle=True) == pytest.approx(np.sqrt(frac) / 2.0)
    # Texels outside the mask do not count.
    est = truth.copy()
    est[~mask] = 1e6
    assert relative_rmse(est, truth, mask) == 0.0


def test_best_scale_and_scale_invariant_metrics():
    truth = sky(16) + blob(16, 0.6, 2.0)
    mask = upper_mask(16)
    est = truth / 3.0
    assert best_scale(est, truth, mask) == pytest.approx(3.0)
    plain = envmap_metrics(est, truth, mask)
    inv = envmap_metrics(est, truth, mask, scale_invariant=True)
    t = truth[mask]
    assert plain["relative_rmse"] == pytest.approx(2.0 / 3.0 * np.sqrt(np.mean(t**2)) / np.mean(t))
    assert plain["scale"] == 1.0 and plain["best_scale"] == pytest.approx(3.0)
    assert inv["relative_rmse"] == pytest.approx(0.0, abs=1e-12)
    assert inv["ssim"] == pytest.approx(1.0)
    assert inv["scale"] == pytest.approx(3.0)
    assert plain["ssim"] < 0.99
    # Least squares with noise: the scale of est = 2 * truth + zero-mean noise orthogonal to truth is 1/2.
    rng = np.random.default_rng(0)
    noise = rng.standard_normal(truth.shape)
    noise -= (np.sum(noise[mask] * truth[mask]) / np.sum(truth[mask] ** 2)) * truth
    assert best_scale(2 * truth + noise, truth, mask) == pytest.approx(
        2 * np.sum(truth[mask] ** 2) / np.sum((2 * truth + noise)[mask] ** 2))
    assert best_scale(np.zeros_like(truth), truth, mask) == 1.0


def test_identical_maps():
    truth = sky(16) + blob(16, 0.5, 1.0)
    m = envmap_metrics(truth, truth, upper_mask(16))
    assert set(m) == {"relative_rmse", "relative_rmse_solid_angle", "tonemapped_rmse", "ssim", "ssim_masked",
                      "brightest_angle_deg",
                      "scale", "best_scale"}
    assert all(type(v) is float for v in m.values())
    assert m["relative_rmse"] == 0.0 and m["tonemapped_rmse"] == 0.0
    assert m["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert m["brightest_angle_deg"] == pytest.approx(0.0, abs=1e-9)


# ---------------------------------------------------------------------------------------------------- tonemap


def test_tonemap_uses_truth_percentile():
    h = 8
    truth = np.linspace(0.5, 1.5, h)[:, None, None] * np.ones((h, 2 * h, 3))  # a sky brighter towards the horizon
    truth[0, 0] = 1000.0  # 3 of 384 values: above the 99th percentile
    mask = np.ones((h, 2 * h), bool)
    s = tonemap_scale(truth, mask)
    assert s == pytest.approx(np.percentile(truth, 99))
    assert s == pytest.approx(1.5)
    t = tonemap(truth * 0.5, s)
    assert t[-1, 1, 0] == pytest.approx(0.5 ** (1 / 2.2))
    assert t[0, 0, 0] == 1.0
    assert tonemap_scale(np.zeros((h, 2 * h, 3)), mask) == 1.0


def test_a_flat_background_is_not_the_tonemaps_white():
    """A dark room: uniform walls and two lamps on 0.3% of the sky. Its 99th percentile is the walls' value, which
    would tonemap the truth to one flat white that the constant map matches (SSIM 1: a metric that cannot fail);
    the tonemap's white is the brightest lamp instead, and the flat maps score far below the truth."""
    from objcam.baselines import baseline_metrics

    h = 32
    truth = np.full((h, 2 * h, 3), 0.01)
    truth[3, 5:7] = 1e3  # a lamp
    truth[6, 20] = 10.0  # a dimmer one
    mask = np.zeros((h, 2 * h), bool)
    mask[: h // 2] = True
    assert np.mean(truth[mask] >= np.percentile(truth[mask], 99)) > 0.9  # the percentile is the walls' value
    assert tonemap_scale(truth, mask) == 1e3
    b = baseline_metrics(truth, mask)
    assert b["constant"]["ssim"] < 0.5 and b["row_mean"]["ssim"] < 0.8
    assert envmap_metrics(truth, truth, mask)["ssim"] == pytest.approx(1.0)
    # the test of the test: the plain percentile scores the constant map as the truth itself
    s = float(np.percentile(truth[mask], 99))
    flat = np.broadcast_to(truth[mask].mean(axis=0), truth.shape)
    assert ssim(np.where(mask[..., None], tonemap(flat, s), 0), np.where(mask[..., None], tonemap(truth, s), 0),
                mask) == pytest.approx(1.0)
    # noisy walls (a chrome ball's truth) sit just under their percentile: still a plateau
    noisy = truth * (1.0 + 0.01 * np.random.default_rng(0).normal(size=truth.shape))
    assert np.mean(noisy[mask] >= np.percentile(noisy[mask], 99)) < 0.02  # no exact plateau
    assert tonemap_scale(noisy, mask) == noisy[mask].max()
    # a sky a quarter brighter at the horizon than at the zenith keeps its percentile (a quarter of its values
    # within 5% of it)
    grad = np.linspace(1.0, 1.5, h)[:, None, None] * np.ones((h, 2 * h, 3))
    assert tonemap_scale(grad, mask) == pytest.approx(np.percentile(grad[mask], 99))


# ---------------------------------------------------------------------------------------------------- SSIM


def _ssim_reference(a, b, sigma=1.5, radius=5, c1=1e-4, c2=9e-4):
    """Direct per-texel loops over the window, sampling spherical neighbours explicitly."""
    h, w = a.shape
    r = min(radius, h)
    k = np.arange(-r, r + 1)
    g = np.exp(-0.5 * (k / sigma) ** 2)
    g /= g.sum()
    out = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            sa = sb = saa = sbb = sab = 0.0
            for di, gi in zip(k, g):
                for dj, gj in zip(k, g):
                    ii, jj = i + di, j + dj
                    if ii < 0:
                        ii, jj = -ii - 1, jj + w // 2
                    elif ii >= h:
                        ii, jj = 2 * h - 1 - ii, jj + w // 2
                    jj %= w
                    wt = gi * gj
                    x, y = a[ii, jj], b[ii, jj]
                    sa += wt * x
                    sb += wt * y
                    saa += wt * x * x
                    sbb += wt * y * y
                    sab += wt * x * y
            va, vb, cov = saa - sa * sa, sbb - sb * sb, sab - sa * sb
            out[i, j] = ((2 * sa * sb + c1) * (2 * cov + c2)) / ((sa * sa + sb * sb + c1) * (va + vb + c2))
    return out


def test_ssim_matches_direct_reference():
    rng = np.random.default_rng(1)
    a = rng.random((6, 12))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    assert np.allclose(ssim_map(a, b), _ssim_reference(a, b), rtol=1e-10, atol=1e-12)
    # Grid shorter than the window radius: the window shrinks to the height.
    a3, b3 = a[:3, :6], b[:3, :6]
    assert np.allclose(ssim_map(a3, b3), _ssim_reference(a3, b3), rtol=1e-10, atol=1e-12)


def test_ssim_known_values_and_monotone_in_noise():
    h = 16
    x = tonemap(sky(h), 1.5)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    # Constant images a and b: SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    a, b, c1 = 0.3, 0.6, 1e-4
    ca, cb = np.full((h, 2 * h), a), np.full((h, 2 * h), b)
    assert ssim(ca, cb) == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-12)
    rng = np.random.default_rng(2)
    n = rng.standard_normal(x.shape)
    vals = [ssim(x, np.clip(x + s * n, 0, 1), upper_mask(h)) for s in (0.0, 0.01, 0.05, 0.2)]
    assert vals[0] == pytest.approx(1.0)
    assert all(v1 > v2 for v1, v2 in zip(vals, vals[1:]))
    assert vals[-1] < 0.5


def test_pad_sphere_continues_across_poles_and_seam():
    h, w = 4, 8
    img = np.arange(h * w, dtype=float).reshape(h, w)
    p = pad_sphere(img, 2)
    assert p.shape == (h + 4, w + 4)
    # Above row 0, column c: row 0, column c + W/2. Two above: row 1.
    assert p[1, 2 + 3] == img[0, (3 + w // 2) % w]
    assert p[0, 2 + 3] == img[1, (3 + w // 2) % w]
    # Below the last row likewise; left of column 0: column W-1.
    assert p[2 + h, 2 + 1] == img[h - 1, (1 + w // 2) % w]
    assert p[2 + 0, 1] == img[0, w - 1]
    assert p[2 + 1, 2 + w] == img[1, 0]


# ------------------------------------------------------------------------------------------------ peak direction


def test_peak_direction_single_texel_and_shift():
    h = 16
    grid = EnvGrid(h)
    dirs = grid.directions()
    truth = 0.01 * sky(h)
    truth[3, 10] = 100.0
    est = 0.01 * sky(h)
    est[5, 13] = 100.0
    mask = upper_mask(h)
    assert np.allclose(brightest_direction(truth, mask), dirs[3, 10])
    assert brightest_angle_deg(est, truth, mask) == pytest.approx(angle_deg(dirs[5, 13], dirs[3, 10]))
    # A symmetric blob rotated by k texels in azimuth moves by exactly k * 360 / W degrees at the equator.
    b = blob(h, np.pi / 2 - 1e-9, 1.0) + 0.01
    full = np.ones((h, 2 * h), bool)
    for k in (1, 3):
        shifted = rotate_z(b, k * 360.0 / grid.width)
        assert brightest_angle_deg(shifted, b, full) == pytest.approx(k * 360.0 / grid.width, abs=1e-6)


def test_peak_direction_refines_between_texels_and_wraps_the_seam():
    h = 16
    grid = EnvGrid(h)
    w = grid.width
    env = np.full((h, w, 3), 0.01)
    # Two equal texels either side of the azimuth seam: the source is at phi = 0 exactly.
    env[4, 0] = env[4, w - 1] = 50.0
    d = brightest_direction(env)
    theta4, half = np.pi * 4.5 / h, np.pi / w  # the two centres sit at phi = +-half
    expect = np.array([np.cos(half) * np.sin(theta4), 0.0, np.cos(theta4)])
    assert np.allclose(d, expect / np.linalg.norm(expect), atol=1e-12)
    # A weaker texel below 50% of the peak does not pull the direction.
    env[5, 0] = 20.0
    assert np.allclose(brightest_direction(env), d)
    # The masked-out texel is ignored even if brighter.
    env[12, 3] = 1e4
    mask = upper_mask(h)
    assert np.allclose(brightest_direction(env, mask), d)
    assert np.all(np.isnan(brightest_direction(np.zeros((h, w, 3)))))


# ------------------------------------------------------------------------------------------------- image space


def test_image_relative_rmse():
    target = np.full((4, 5, 3), 2.0)
    pred = target.copy()
    pred[0, 0] = 2.0 + 4.0  # one bad pixel
    valid = np.ones((4, 5), bool)
    assert image_relative_rmse(pred, target, valid) == pytest.approx(np.sqrt(16.0 / 20.0) / 2.0)
    valid[0, 0] = False
    assert image_relative_rmse(pred, target, valid) == 0.0
    # (M, C) pixel lists with an (M,) mask.
    assert image_relative_rmse(pred.reshape(-1, 3), target.reshape(-1, 3), valid.ravel()) == 0.0
    with pytest.raises(ValueError):
        image_relative_rmse(pred, target[:2])
