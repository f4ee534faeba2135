"""The albedo's total-variation step (objcam.solvers.albedo_tv): the ROF solver against closed forms and nearby
points, and the step on a shaded piecewise-constant support with a low-contrast error pressed into it."""

from __future__ import annotations

import numpy as np
import pytest

from objcam.solvers.albedo_tv import ImageGraph, rof_graph, tv_albedo


def _rof_objective(u, f, w, graph, lam):
    gh, gv = graph.grad(graph.to_grid(u))
    tv = np.sqrt((gh**2).sum(-1)).sum() + np.sqrt((gv**2).sum(-1)).sum()
    return 0.5 * float(np.sum(w * (u - f) ** 2)) + lam * tv


@pytest.mark.parametrize("f2", [0.2, 0.5])
def test_two_pixels_match_the_closed_form(f2):
    """Two pixels, one edge: u1, u2 each move lam / w toward the other while they stay apart, else they meet at
    the weighted mean."""
    f, w, lam = np.array([[0.6], [f2]]), np.array([[2.0], [1.0]]), 0.1
    graph = ImageGraph(np.array([0, 1]), (1, 2), np.ones(2, bool))
    u, _, it, _ = rof_graph(f, w, graph, lam, np.ones(2, bool), max_iter=20000, tol=1e-12)
    if f[0, 0] - f2 > lam * (1 / w[0, 0] + 1 / w[1, 0]):  # f2 = 0.2: 0.4 > 0.15, they stay apart
        want = [0.6 - lam / 2.0, f2 + lam / 1.0]
    else:  # f2 = 0.5: 0.1 < 0.15, they meet
        want = [(2 * 0.6 + f2) / 3] * 2
    np.testing.assert_allclose(u[:, 0], want, atol=1e-6)


def test_the_minimiser_beats_nearby_points_and_holds_fixed_pixels():
    rng = np.random.default_rng(0)
    h, wd, C = 9, 11, 3
    pix = rng.permutation(h * wd)[:80]  # some image pixels are not rows (holes)
    free = rng.random(80) > 0.15
    f = rng.uniform(0.05, 0.95, (80, C))
    w = rng.uniform(0.5, 3.0, (80, C))
    graph = ImageGraph(pix, (h, wd), free)
    lam = 0.05
    u, _, it, change = rof_graph(f, w, graph, lam, free, max_iter=20000, tol=1e-10)
    assert change < 1e-10
    np.testing.assert_array_equal(u[~free], f[~free])
    assert u.min() >= 1e-3 - 1e-12 and u.max() <= 1.0 + 1e-12
    best = _rof_objective(u, f, w, graph, lam)
    for _ in range(50):
        v = u.copy()
        v[free] = np.clip(v[free] + 1e-3 * rng.standard_normal((free.sum(), C)), 1e-3, 1.0)
        assert _rof_objective(v, f, w, graph, lam) >= best - 1e-12


def test_the_step_removes_a_faint_shadow_absorbed_into_the_albedo_and_keeps_the_print():
    """A support of two albedos (a disc of 0.3 on 0.7) under three lights; the albedo the data give is the truth
    plus a 3-pixel wide streak of +0.4% (what a free per-pixel albedo absorbs from a misplaced penumbra). The TV
    step at contrast 0.008 takes most of the streak out and, refitting the regions it finds, gives the disc its
    exact albedo back."""
    h = w = 40
    yy, xx = np.mgrid[0:h, 0:w]
    truth = np.where((yy - 20) ** 2 + (xx - 14) ** 2 < 64, 0.3, 0.7)
    band = np.abs(xx - 28) < 2
    streak = np.where(band, 0.004, 0.0) * truth
    M, N, L = h * w, 6, 3
    rng = np.random.default_rng(1)
    A = rng.uniform(0.5, 1.5, (M, N)).astype(np.float32)  # the shading of albedo 1
    X = rng.uniform(0.5, 1.0, (N, L, 1))
    S = np.einsum("mn,nlc->mlc", A.astype(np.float64), X)
    Y = (truth + streak).reshape(-1)[:, None, None] * S  # data that a free albedo fits with the streak in it
    fixed = np.zeros(M, bool)
    rho0 = np.full((M, 1), 0.5)
    res = tv_albedo(A, Y, X, rho0, fixed, np.arange(M), (h, w), contrast=0.008)
    rho = res.rho[:, 0].reshape(h, w)
    # the streak (0.0028) is gone: what is left is spread over its side of the image (measured 0.0002)
    err = rho - truth
    assert np.abs(err[band]).max() < 0.2 * streak.max(), np.abs(err[band]).max()
    # the disc keeps its albedo and its edge: TV alone lowers its contrast by about lam x perimeter / (w x area)
    # (0.0017 at its rim), the regions' least-squares refit takes that back (measured 4e-16 inside the disc)
    disc = (yy - 20) ** 2 + (xx - 14) ** 2 < 64
    assert res.regions < 10 and np.abs(err[disc]).max() < 1e-9
    assert np.abs(err).max() < 0.1 * streak.max()
    raw = tv_albedo(A, Y, X, rho0, fixed, np.arange(M), (h, w), contrast=0.008, refit=False)
    err_raw = raw.rho[:, 0].reshape(h, w) - truth
    assert raw.regions is None and np.abs(err_raw[disc]).max() > 1e-3  # TV's own contrast loss
    assert np.abs(err_raw[band]).max() < 0.2 * streak.max()
    # the least-squares albedo of each pixel is the fit's starting point: without the prior it comes back
    res0 = tv_albedo(A, Y, X, rho0, fixed, np.arange(M), (h, w), contrast=0.0)
    np.testing.assert_allclose(res0.rho[:, 0], (truth + streak).reshape(-1), rtol=1e-5)


def test_regions_and_their_least_squares_refit():
    """ImageGraph.regions joins neighbours that differ by less than tol; refit_regions gives each region the
    weighted mean of f (the data term's minimiser among region-constant albedos), leaving fixed pixels alone."""
    from objcam.solvers.albedo_tv import refit_regions

    u = np.array([[0.5], [0.5004], [0.8], [0.8], [0.3], [0.3]])  # a 2 x 3 image, rows in image order
    free = np.array([True, True, True, True, True, False])
    graph = ImageGraph(np.arange(6), (2, 3), free)
    labels, n = graph.regions(u, tol=1e-3)
    # rows 0 and 1 are joined (0.0004 < 1e-3); every other pair of neighbours differs; row 5 is fixed: its own
    assert labels[0] == labels[1] and len({labels[2], labels[3], labels[4], labels[0]}) == 4 and n == 5
    f = np.array([[0.4], [0.7], [0.8], [0.9], [0.2], [0.3]])
    w = np.array([[1.0], [3.0], [1.0], [1.0], [2.0], [1.0]])
    out = refit_regions(u, f, w, labels, n, free)
    np.testing.assert_allclose(out[:2, 0], (0.4 * 1 + 0.7 * 3) / 4)
    np.testing.assert_allclose(out[2:5, 0], [0.8, 0.9, 0.2])
    assert out[5, 0] == u[5, 0]
