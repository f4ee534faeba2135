"""The photo's own noise where a target states none (objcam.transport.auto.estimate_pixel_noise): edges and
texture are not noise. The mean-|Laplacian| reading (estimate_relative_noise), which counts them, stays the
prior's weight (bench/results.md, session 54)."""

import numpy as np
import pytest

from objcam.transport.auto import estimate_pixel_noise, estimate_relative_noise

H, W = 120, 160


def _scene(square: int) -> np.ndarray:
    """(H, W) clean linear image: smooth light across a printed checkerboard of ``square``-pixel squares (albedo
    0.05 on 0.8 paper), as a photographed capture's board; square 0: plain paper."""
    yy, xx = np.mgrid[0:H, 0:W]
    albedo = np.full((H, W), 0.8) if square == 0 else np.where((yy // square + xx // square) % 2 == 0, 0.05, 0.8)
    return (0.5 + 0.5 * xx / W) * albedo


@pytest.mark.parametrize("square", [0, 8, 16])
@pytest.mark.parametrize("sigma_rel", [0.005, 0.02])
def test_the_photo_noise_is_read_at_the_median_pixel_through_a_printed_board(square, sigma_rel):
    clean = _scene(square)
    rng = np.random.default_rng(7)
    img = np.stack([clean + rng.normal(0.0, sigma_rel * np.median(clean), clean.shape) for _ in range(3)], axis=-1)
    valid = np.ones((H, W), bool)
    assert estimate_pixel_noise(img, valid) == pytest.approx(sigma_rel, rel=0.12)
    if square == 8:  # the mean |Laplacian| counts the board's edges: 2.8-9x the noise
        assert estimate_relative_noise(img, valid) > 2.5 * sigma_rel


def test_noise_that_grows_with_brightness_is_read_at_the_median_pixel():
    clean = _scene(0) * np.linspace(0.2, 3.0, W)[None, :]  # a 15:1 ramp of brightness
    med = np.median(clean)
    sigma = 0.02 * med * np.sqrt(clean / med)  # shot noise: 2% at the median pixel
    img = (clean + np.random.default_rng(3).normal(0.0, 1.0, clean.shape) * sigma)[..., None]
    assert estimate_pixel_noise(img, np.ones((H, W), bool)) == pytest.approx(0.02, rel=0.12)


def test_too_few_pixels_give_no_estimate():
    img = np.random.default_rng(0).normal(1.0, 0.01, (H, W, 3))
    small = np.zeros((H, W), bool)
    small[:8, :8] = True  # 36 pixels with a whole 3 x 3 neighbourhood
    assert estimate_pixel_noise(img, small) is None
    assert estimate_pixel_noise(img, np.ones((H, W), bool)) == pytest.approx(0.01, rel=0.1)
