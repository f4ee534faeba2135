"""objcam.solvers.refine: the supersampled solve's adaptive basis, its contrast split and the area average back to
the output grid; and, on a renderer-free scene whose sun sits inside one fine texel, that refining where a pilot
solve sees contrast recovers what the output grid's box texels cannot."""

from __future__ import annotations

import numpy as np
import pytest

from objcam.envmap import EnvGrid, area_downsample
from objcam.solvers import difference_operator, gram
from objcam.solvers.basis import texel_basis
from objcam.solvers.edges import solve_edges
from objcam.solvers.refine import average_to, coarse_of, contrast, refined_basis, split_by_contrast
from objcam.solvers.regularization import absolute_weights
from tests.toy_scenes import sphere_shadow_transport

H = 8  # output rows; A's grid has 2H


def test_average_to_is_the_area_average_over_kept_texels():
    fine = EnvGrid(2 * H)
    env = np.random.default_rng(0).uniform(0.1, 2.0, size=(*fine.shape, 3))
    full = np.ones(fine.shape, bool)
    out, m = average_to(env, full, H)
    np.testing.assert_allclose(out, area_downsample(env, H), rtol=1e-12)
    assert m.all()
    # the integral of radiance x solid angle is kept
    np.testing.assert_allclose((out * EnvGrid(H).solid_angles()[..., None]).sum((0, 1)),
                               (env * fine.solid_angles()[..., None]).sum((0, 1)), rtol=1e-12)
    # unkept fine texels do not enter the mean; an output texel with none kept is unsolved
    mask = full.copy()
    mask[0, 0] = False  # one of output texel (0, 0)'s four
    mask[2:4, 4:6] = False  # all of output texel (1, 2)'s
    out, m = average_to(env, mask, H)
    w = fine.solid_angles()[:2, :2] * mask[:2, :2]
    np.testing.assert_allclose(out[0, 0], (env[:2, :2] * w[..., None]).sum((0, 1)) / w.sum(), rtol=1e-12)
    assert m[0, 0] and not m[1, 2] and np.all(out[1, 2] == 0)
    with pytest.raises(ValueError, match="multiple"):
        average_to(env[:15, :30], mask[:15, :30], H)


def test_refined_basis_groups():
    fine = EnvGrid(2 * H)
    keep = np.flatnonzero(fine.directions().reshape(-1, 3)[:, 2] > 0)
    cidx, member = coarse_of(fine, keep, H)
    assert cidx.size == keep.size // 4 and np.bincount(member).tolist() == [4] * cidx.size
    for g in (0.0, 1.0):
        none = refined_basis(fine, keep, H, np.zeros(cidx.size, bool), g)
        every = refined_basis(fine, keep, H, np.ones(cidx.size, bool), g)
        # every fine texel in exactly one group
        for P in (none, every):
            assert np.all(np.asarray(P.sum(axis=1)).ravel() == 1)
        # nothing split: the output grid's (merged) basis; everything split: the fine grid's
        Pc = texel_basis(EnvGrid(H), cidx, g)
        Pf = texel_basis(fine, keep, g)
        assert none.shape[1] == (cidx.size if Pc is None else Pc.shape[1])
        assert every.shape[1] == (keep.size if Pf is None else Pf.shape[1])
        # a group never straddles two output texels
        gid = np.asarray(none.argmax(axis=1)).ravel()
        for k in np.unique(gid):
            assert len(np.unique(cidx[member[gid == k]] // (2 * H))) == 1  # one output row
    split = np.zeros(cidx.size, bool)
    split[[3, 40]] = True
    P = refined_basis(fine, keep, H, split, 0.0)
    assert P.shape[1] == cidx.size + 2 * 3  # two output texels become four unknowns each


def test_contrast_finds_the_edges():
    fine = EnvGrid(2 * H)
    keep = np.flatnonzero(fine.directions().reshape(-1, 3)[:, 2] > 0)
    cidx, _ = coarse_of(fine, keep, H)
    env = np.ones((*fine.shape, 3))
    env[:, 10:] = 50.0  # a step at output column 5 (and the seam)
    s = contrast(fine, keep, H, env.reshape(-1, 3)[keep])
    cols = cidx % (2 * H)
    at_edge = np.isin(cols, [4, 5, 0, 15])
    assert s[~at_edge].max() < 1e-12 < s[at_edge].min()
    split = split_by_contrast(s, at_edge.mean())
    assert np.array_equal(split, at_edge)
    assert not split_by_contrast(s, 0.0).any() and split_by_contrast(s, 1.0).all()


def _sun_in_a_fine_texel():
    fine = EnvGrid(2 * H)
    keep, A = sphere_shadow_transport(fine, 40)
    theta, phi = fine.centres()
    sky = (0.5 + 0.5 * np.cos(theta)) * (1 + 0.3 * np.cos(phi))
    truth = np.stack([sky, 0.9 * sky, 1.2 * sky], -1)
    mean = truth.reshape(-1, 3)[keep].mean()
    truth[5, 9] += 60 * mean * np.array([1.0, 0.95, 0.8])  # one of output texel (2, 4)'s four
    truth[3, 20:23] += 5 * mean  # a thin bright streak
    return fine, keep, A, truth


def _refine_errors(which: str = "pilot") -> tuple[float, float, bool]:
    """(error with the output grid's box texels, error refined where ``which`` says, whether the sun's output
    texel was refined) on :func:`_sun_in_a_fine_texel`. ``which``: "pilot" (split where the pilot solve sees
    contrast, the method), or the broken "none" (nothing split) and "away" (as many texels split, the pilot's
    least contrasted ones)."""
    fine, keep, A, truth = _sun_in_a_fine_texel()
    x = truth.reshape(-1, 3)[keep]
    y0 = A.astype(np.float64) @ x
    sigma = 1e-3
    y = y0 + sigma * np.abs(y0).mean() * np.random.default_rng(0).normal(size=y0.shape)
    G, B, yy = gram(A), A.T.astype(np.float64) @ y, (y * y).sum(0)
    D = difference_operator(fine, keep)
    ls, lr = absolute_weights(G, 10 * sigma, 1e-4)
    mask = np.zeros(fine.n_texels, bool)
    mask[keep] = True
    mask = mask.reshape(fine.shape)
    t_out, m_out = average_to(truth, mask, H)

    def error(P):
        r = solve_edges([G], [B], [[0, 1, 2]], yy, D, ls, lr, steps=6, eps_rel=1e-3, tone=0.3, basis=P)
        env = np.zeros((fine.n_texels, 3))
        env[keep] = r.x
        est, _ = average_to(env.reshape(*fine.shape, 3), mask, H)
        return float(np.sqrt(np.mean((est - t_out)[m_out] ** 2)) / t_out[m_out].mean())

    cidx, _ = coarse_of(fine, keep, H)
    P0 = refined_basis(fine, keep, H, np.zeros(cidx.size, bool), 1.0)
    pilot = solve_edges([G], [B], [[0, 1, 2]], yy, D, ls, lr, steps=0, basis=P0)
    s = contrast(fine, keep, H, pilot.x)
    split = split_by_contrast(s, 0.2)
    if which == "none":
        split = np.zeros_like(split)
    elif which == "away":
        split = np.zeros_like(split)
        split[np.argsort(s)[:int(split_by_contrast(s, 0.2).sum())]] = True
    sun = bool(split[np.searchsorted(cidx, 2 * 2 * H + 4)])
    return error(P0), error(refined_basis(fine, keep, H, split, 1.0)), sun


def test_refining_where_the_pilot_sees_contrast_recovers_the_sun():
    e_box, e_refined, sun = _refine_errors()
    assert sun  # the sun's output texel is refined
    # measured: 1.22 on the output texels (the sun spread over its texel moves its shadows) against 0.068
    assert e_box > 0.8
    assert e_refined < 0.1 * e_box and e_refined < 0.1


@pytest.mark.parametrize("which", ["none", "away"])
def test_refining_in_the_wrong_place_fails_the_bounds(which):
    """A test of the test (tests/broken.py): nothing refined, or as many texels refined where the pilot sees the
    least contrast, leaves the sun's error (measured 1.22 and 1.22, against 0.068)."""
    _, e_refined, sun = _refine_errors(which)
    assert not sun and not (e_refined < 0.1), e_refined
