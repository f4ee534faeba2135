"""The known-albedo edge prior's ridge follows the noise (objcam.solvers.plan.rules.noise_lr, issue 22): lr =
DEFAULT_LR_REL x min(1, sigma / LR_SIGMA_REF), so on a quiet photo the ridge no longer outweighs the data and pulls a
lamp's peak and the weakly seen texels towards zero."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from objcam.envmap import EnvGrid
from objcam.metrics import relative_rmse
from objcam.solvers.plan.defaults import LR_SIGMA_REF
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.rules import noise_lr, noise_ls, noise_weights
from objcam.solvers.regularization import DEFAULT_LR_REL


def test_noise_lr_rule():
    for sigma, want in ((LR_SIGMA_REF, DEFAULT_LR_REL), (LR_SIGMA_REF / 4, DEFAULT_LR_REL / 4),
                        (0.001, DEFAULT_LR_REL * 0.001 / LR_SIGMA_REF), (5 * LR_SIGMA_REF, DEFAULT_LR_REL)):
        assert noise_lr(sigma) == pytest.approx(want)  # never above the default
    assert noise_lr(None) == DEFAULT_LR_REL  # noise unknown


def test_noise_weights_estimate_the_noise_once_for_both():
    """ls as noise_ls gives it, lr from the same noise per fitted pixel: the stated noise is per photo pixel, so
    over 2 x 2 pooling a fitted pixel has half of it."""
    ok, img, p = np.ones((4, 4), bool), np.ones((4, 4, 3)), SolveParams()
    target = SimpleNamespace(noise_sigma=0.01)
    ls, lr, source = noise_weights(target, img, ok, p, f=2, linear=True)
    assert (ls, source) == noise_ls(target, img, ok, p, f=2, linear=True)
    assert lr == pytest.approx(DEFAULT_LR_REL * 0.25)


def _solve(noise: float, **params):
    """(truth (H, 2H, 3), solved texels (H, 2H) bool, the known solve) of a lamp near the horizon over an
    elevation-graded sky, the shadows of three spheres on a plane (tests.toy_scenes.sphere_shadow_toy), photographed
    with ``noise`` relative Gaussian noise, stated as such; ``params``: SolveParams."""
    from objcam.solvers.plan.known import _solve_target
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.targets import TargetData
    from tests.toy_scenes import sphere_shadow_toy

    grid = EnvGrid(16)
    tr, keep = sphere_shadow_toy(grid, 40)
    theta, _ = grid.centres()
    truth = np.repeat((0.05 + 0.05 * np.cos(theta))[..., None], 3, axis=2)
    truth[7, 3] += 120.0  # ~17 deg above the horizon
    clean = tr.predict(tr.x_from_envmap(truth))
    photo = clean + noise * np.median(clean[clean > 0]) * np.random.default_rng(0).normal(size=clean.shape)
    y = photo.reshape(-1, 3)[tr.pixel_index].astype(np.float64)
    d = TargetData(tr, photo, np.ones(photo.shape[:2], bool), y, np.ones(len(y), bool))
    sol = _solve_target(SimpleNamespace(noise_sigma=noise, name="t"), d, SolveParams(**params), {})
    mask = np.zeros(truth.shape[:2], bool)
    mask.reshape(-1)[keep] = True
    return truth, mask, sol


def test_a_quiet_photo_gets_a_smaller_ridge_and_a_closer_map():
    """At 0.1% noise the rule's ridge is 5e-6 (recorded in solve.json) and the lamp comes back whole: relative RMSE
    0.03 (measured); the former fixed ridge (lr 1e-4, the broken setting) held the lamp's peak down: 0.42."""
    truth, mask, sol = _solve(0.001)
    assert sol.info["lr_relative"] == pytest.approx(DEFAULT_LR_REL * 0.001 / LR_SIGMA_REF)
    err = relative_rmse(sol.envmap, truth, mask)
    _, _, fixed = _solve(0.001, lr=DEFAULT_LR_REL)
    assert fixed.info["lr_relative"] == DEFAULT_LR_REL
    err_fixed = relative_rmse(fixed.envmap, truth, mask)
    assert err < 0.1 < 0.3 < err_fixed, (err, err_fixed)


def test_at_the_reference_noise_the_ridge_is_the_former_default():
    """At 2% noise per fitted pixel the rule gives the fixed ridge the solve had before (the same map)."""
    truth, mask, sol = _solve(LR_SIGMA_REF)
    _, _, fixed = _solve(LR_SIGMA_REF, lr=DEFAULT_LR_REL)
    assert sol.info["lr_relative"] == pytest.approx(DEFAULT_LR_REL)
    np.testing.assert_allclose(sol.envmap, fixed.envmap, rtol=1e-9, atol=1e-12)
