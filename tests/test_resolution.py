"""The prior's weight across envmap heights (objcam.solvers.plan.rules.height_factor): the same continuous prior
at every height, so a finer envmap is not solved under a 16x weaker prior."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from objcam.envmap import EnvGrid
from objcam.solvers import absolute_weights, difference_operator
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.rules import height_factor, noise_ls


@pytest.mark.parametrize("linear", [False, True])
def test_noise_ls_scales_with_the_fourth_power_of_the_height(linear):
    target = SimpleNamespace(noise_sigma=0.02, name="t0")
    img, ok = np.ones((4, 4, 3)), np.ones((4, 4), bool)
    p = SolveParams()
    base, src = noise_ls(target, img, ok, p, 1, linear=linear)
    fine, src64 = noise_ls(target, img, ok, p, 1, linear=linear, height=64)
    assert fine == pytest.approx(16 * base) and "x 16 for 64 rows" in src64 and "rows" not in src
    assert noise_ls(target, img, ok, p, 1, linear=linear, height=16)[0] == pytest.approx(base / 16)


def test_height_factor_keeps_the_absolute_prior_of_a_smooth_sky():
    """The derivation behind the factor, checked: for a smooth radiance function sampled at H and 2H, A's columns
    (texel solid angles) shrink the relative unit mean(diag A^T A) ~16x, ||D x||^2 stays, so ls_rel x 16 keeps
    ls_abs ||D x||^2 within a few percent."""
    out, plain = {}, {}
    for h in (16, 32):
        grid = EnvGrid(h)
        keep = np.flatnonzero(grid.directions().reshape(-1, 3)[:, 2] > 0)
        theta, phi = grid.centres()
        x = (np.cos(theta) + 0.5 * np.sin(theta) * np.cos(phi)).ravel()[keep]
        omega = grid.solid_angles().ravel()[keep]
        rng = np.random.default_rng(0)
        dirs = grid.directions().reshape(-1, 3)[keep]
        # 400 pixels that each see a random cap of the sky: columns proportional to the texel's solid angle
        axes = rng.normal(size=(400, 3))
        A = ((axes @ dirs.T) > 0) * omega[None] * dirs[None, :, 2]
        ls_abs, _ = absolute_weights(A.T @ A, 1.0 * height_factor(h), 0.0)
        D = difference_operator(grid, keep)
        out[h] = ls_abs * float(np.sum((D @ x) ** 2))
        plain[h] = absolute_weights(A.T @ A, 1.0, 0.0)[0] * float(np.sum((D @ x) ** 2))
    assert out[32] == pytest.approx(out[16], rel=0.1)
    # a test of the test (tests/broken.py): without the height factor (ls_rel 1 at both heights) it misses
    assert not plain[32] == pytest.approx(plain[16], rel=0.1), plain
