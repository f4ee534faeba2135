"""objcam.solvers.sources (solve.sources=compact, issue 22): a bright blob the data cannot place becomes a point
source within the fit's chi-squared spread; a bright region the data do place is left alone."""

from __future__ import annotations

import numpy as np

from objcam.metrics import ssim, tonemap, tonemap_scale
from objcam.solvers.sources import compact_sources
from tests.toy_scenes import lobe_scene

H = 16


def _scene(seed: int, visibility: float | None):
    return lobe_scene(seed, visibility, H)


def _data(A: np.ndarray, x: np.ndarray, rng, noise: float = 0.01) -> np.ndarray:
    y = A[0].astype(np.float64) @ x
    return y + noise * np.median(y) * rng.normal(size=y.shape)


def _env(x: np.ndarray, texel_index: np.ndarray) -> np.ndarray:
    env = np.zeros((H * 2 * H, 3))
    env[texel_index] = x
    return env.reshape(H, 2 * H, 3)


def _tm_ssim(x: np.ndarray, truth: np.ndarray, texel_index: np.ndarray) -> float:
    t = _env(truth, texel_index)
    s = tonemap_scale(t)
    return ssim(tonemap(_env(x, texel_index), s), tonemap(t, s))


def test_a_lamp_the_data_cannot_place_becomes_a_point():
    grid, ti, A, rng = _scene(0, None)
    W = grid.width
    truth = np.repeat(0.2 + 0.1 * (ti // W)[:, None], 3, axis=1)  # a dim sky, brighter towards the horizon
    lamp = 1 * W + 9  # row 1, column 9
    truth[lamp] += 1e3
    y = _data(A, truth, rng)
    # what the edge prior returns: the lamp's energy spread over its 3 x 3 neighbourhood (same centroid)
    spread = truth.copy()
    spread[lamp] -= 1e3
    omega = grid.solid_angles().reshape(-1)[ti]
    hood = [r * W + c for r in (0, 1, 2) for c in (8, 9, 10)]
    spread[hood] += 1e3 * omega[lamp] / (len(hood) * omega[hood])[:, None]
    use = np.ones(y.shape[0], bool)
    got = compact_sources(A, use, y, spread, grid, ti)
    assert got.info["blobs_found"] == 1 and got.info["collapsed"] == 1
    # the misfit does not rise past its own spread
    assert got.info["ss_after"] - got.info["ss_fit"] <= got.info["ss_spread"]
    # the brightest texel is the lamp's, and the tonemapped map is closer to the truth
    assert int(np.argmax(got.x.mean(axis=1))) == lamp
    before, after = _tm_ssim(spread, truth, ti), _tm_ssim(got.x, truth, ti)
    assert after > 0.98 and after > before + 0.03, (before, after)  # measured 0.946 -> 0.992


def test_a_region_the_data_place_is_left_alone():
    grid, ti, A, rng = _scene(1, 0.5)
    W = grid.width
    truth = np.ones((ti.size, 3))
    window = [r * W + c for r in (2, 3, 4) for c in range(10, 15)]
    truth[window] += 100.0  # an extended bright window, 15 texels
    y = _data(A, truth, rng)
    use = np.ones(y.shape[0], bool)
    got = compact_sources(A, use, y, truth, grid, ti)
    assert got.info["blobs_found"] == 1 and got.info["collapsed"] == 0
    assert got.info["blobs"][0]["rise"] > 10 * got.info["ss_spread"]
    np.testing.assert_array_equal(got.x, truth)
