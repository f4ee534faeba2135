"""The trivial baselines (issue 28) and the masked SSIM, on hand-made maps with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from objcam.baselines import baseline_metrics, constant_map, row_mean_map, skill, with_baselines
from objcam.envmap import EnvGrid, rotate_z, spherical_to_direction
from objcam.metrics import envmap_metrics, masked_ssim, ssim, tonemap, tonemap_scale


def sky_with_sun(h: int = 16) -> np.ndarray:
    """(h, 2h, 3): a sky varying in azimuth plus a bright blob, so azimuth carries structure."""
    grid = EnvGrid(h)
    theta, phi = grid.centres()
    base = 0.5 + 0.5 * np.cos(theta) + 0.3 * np.sin(2 * phi) * np.sin(theta)
    d0 = spherical_to_direction(np.float64(0.8), np.float64(1.0))
    ang = np.arccos(np.clip(grid.directions() @ d0, -1, 1))
    sun = 40.0 * np.exp(-0.5 * (ang / np.radians(8.0)) ** 2)
    v = base + sun
    return np.stack([v, 0.9 * v, 1.1 * v], -1)


def upper(h: int) -> np.ndarray:
    m = np.zeros((h, 2 * h), bool)
    m[: h // 2] = True
    return m


def test_constant_and_row_mean_maps_hold_the_truths_means():
    h = 8
    truth = sky_with_sun(h)
    mask = upper(h)
    c = constant_map(truth, mask)
    w = EnvGrid(h).solid_angles()
    # solid-angle weighted mean over the mask, by hand
    want = np.array([(truth[..., k] * w)[mask].sum() / w[mask].sum() for k in range(3)])
    assert np.allclose(c[3, 5], want) and np.allclose(c, c[0, 0])
    r = row_mean_map(truth, mask)
    assert np.allclose(r[2, 7], truth[2].mean(axis=0))
    assert np.all(r[h // 2:] == 0)  # rows with no kept texel


def test_constant_maps_skill_over_itself_is_zero():
    truth = sky_with_sun(16)
    mask = upper(16)
    est = envmap_metrics(constant_map(truth, mask), truth, mask)
    sk = skill(est, baseline_metrics(truth, mask))
    assert sk["ssim_over_constant"] == pytest.approx(0.0, abs=1e-12)
    assert sk["ssim_masked_over_constant"] == pytest.approx(0.0, abs=1e-12)
    assert sk["tonemapped_rmse_over_constant"] == pytest.approx(1.0, abs=1e-12)
    # and over the row-mean map it is not zero: the two baselines differ on this sky (measured +0.20 SSIM: the
    # row-mean map smears the sun along its rows, which SSIM punishes more than a flat map)
    assert abs(sk["ssim_over_row_mean"]) > 0.05


def test_the_truth_beats_both_baselines():
    truth = sky_with_sun(16)
    mask = upper(16)
    m = with_baselines(envmap_metrics(truth, truth, mask), truth, mask)
    assert m["ssim"] == pytest.approx(1.0)
    for b in ("constant", "row_mean"):
        assert m["baselines"][b]["ssim"] < 0.95, m["baselines"][b]
        assert m["skill"][f"ssim_over_{b}"] > 0.05
        assert m["skill"][f"tonemapped_rmse_over_{b}"] == pytest.approx(0.0, abs=1e-12)
    assert m["beats_row_mean"] == {"ssim": True, "tonemapped_rmse": True}


def test_a_rotated_truth_does_not_beat_the_row_mean_oracle():
    truth = sky_with_sun(16)
    mask = upper(16)
    m = with_baselines(envmap_metrics(rotate_z(truth, 90.0), truth, mask), truth, mask)
    # right brightness per elevation, wrong azimuth: no better than knowing the row means
    assert m["skill"]["ssim_over_row_mean"] < 0, m["skill"]
    assert m["skill"]["tonemapped_rmse_over_row_mean"] > 1, m["skill"]
    assert m["beats_row_mean"] == {"ssim": False, "tonemapped_rmse": False}


def test_masked_ssim_ignores_the_unsolved_texels():
    truth = sky_with_sun(16)
    mask = upper(16)
    s = tonemap_scale(truth, mask)
    tt = np.where(mask[..., None], tonemap(truth, s), 0.0)
    # every texel kept: the same number as the zero-filled SSIM
    full = np.ones_like(mask)
    assert masked_ssim(tonemap(truth, s) * 0.8, tonemap(truth, s), full) == pytest.approx(
        ssim(tonemap(truth, s) * 0.8, tonemap(truth, s), full), abs=1e-12)
    # the constant map gets credit from the solved/unsolved border when zero-filled, none when masked
    tc = np.where(mask[..., None], tonemap(constant_map(truth, mask), s), 0.0)
    zeroed, masked = ssim(tc, tt, mask), masked_ssim(tc, tt, mask)
    assert masked < zeroed - 0.05, (masked, zeroed)
    # what lies outside the mask does not change it
    noise = np.random.default_rng(0).random(tt.shape)
    assert masked_ssim(np.where(mask[..., None], tc, noise), tt, mask) == pytest.approx(masked, abs=1e-12)
