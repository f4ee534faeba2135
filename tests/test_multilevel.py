"""Coarse-to-fine warm starts of the exact solves (objcam.solvers.multilevel): the aggregates and the start."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from objcam.envmap import EnvGrid
from objcam.solvers import absolute_weights, difference_operator, regularized_gram, solve_exact
from objcam.solvers.basis import texel_basis
from objcam.solvers.edges import solve_edges
from objcam.solvers.multilevel import aggregates
from tests.toy_scenes import cone_shadow_transport, sky_with_sun

KKT_TOL = 1e-8


def _problem(seed: int = 3, height: int = 16, dark: float = 0.6, ls_rel: float = 1e-3):
    """A shadow-like NNQP on the upper hemisphere of a height x 2 height grid (tests.toy_scenes' occluder cones):
    most of the truth dark and the photo's level lowered, so most of the answer sits at the bound (as in the edge
    prior's solves at 64 x 128)."""
    rng = np.random.default_rng(seed)
    grid = EnvGrid(height)
    keep = np.flatnonzero(grid.directions().reshape(-1, 3)[:, 2] > 0)
    n = keep.size
    A = cone_shadow_transport(grid, keep, 3 * n, rng)
    X = np.tile(sky_with_sun(grid, keep, 30.0).reshape(-1, 3)[keep], 1)
    phi = np.arange(grid.n_texels)[keep] % grid.width / grid.width
    X[(phi + rng.random()) % 1.0 < dark] = 0.0  # a dark wall over that share of the azimuths
    Y = A @ X
    Y += 0.01 * np.abs(Y).mean() * rng.standard_normal(Y.shape) - 0.05 * np.abs(Y).mean()
    G = A.T @ A
    ls, lr = absolute_weights(G, ls_rel, 1e-6)
    D = difference_operator(grid, keep)
    return grid, keep, D, regularized_gram(G, D, ls, lr), A.T @ Y, (G, ls, lr)


def test_aggregates_partition_the_unknowns_into_joined_neighbours():
    grid, keep, D, *_ = _problem()
    P = texel_basis(grid, keep, 1.0)  # merged texel groups near the pole: aggregates follow them
    Dm = sp.csr_matrix(D @ P)
    Pc = aggregates(Dm)
    n = Dm.shape[1]
    assert Pc.shape[0] == n and np.array_equal(np.asarray(Pc.sum(axis=1)).ravel(), np.ones(n))
    sizes = np.asarray(Pc.sum(axis=0)).ravel()
    assert sizes.max() <= 4 and sizes.min() >= 1 and Pc.shape[1] < 0.35 * n  # most join 3-4 neighbours
    adj = (abs(Dm).T @ abs(Dm)).tocsr()
    for a in range(Pc.shape[1]):  # every aggregate is connected through the prior's edges
        members = Pc[:, a].nonzero()[0]
        reached = {members[0]}
        for _ in range(len(members)):
            reached |= {j for i in reached for j in adj[i].indices if j in set(members)}
        assert reached == set(members)


def test_coarse_start_reaches_the_same_minimiser_in_fewer_rounds():
    grid, keep, D, Q, B, _ = _problem()
    cold = solve_exact(Q, B)
    warm = solve_exact(Q, B, coarse=aggregates(D))
    assert np.all(cold.kkt_residual <= KKT_TOL) and np.all(warm.kkt_residual <= KKT_TOL) and warm.converged
    assert (warm.x == 0).mean() > 0.3  # the bound is active: the start matters
    assert np.allclose(warm.x, cold.x, rtol=1e-9, atol=1e-9 * np.abs(cold.x).max())
    assert "coarse_start_seconds" in warm.info
    assert warm.iterations < cold.iterations and warm.info["factorizations"] < cold.info["factorizations"]
    # a given free set wins over the coarse start: from the answer, one round
    again = solve_exact(Q, B, coarse=aggregates(D), passive0=warm.x > 0)
    assert again.iterations == 1 and "coarse_start_seconds" not in again.info


def test_edge_solve_with_coarse_starts_matches_the_cold_one():
    """solve_edges starts its first solves from the coarse problem: the reweighted steps end where cold ones do."""
    grid, keep, D, _, B, (G, ls, lr) = _problem(seed=5)
    yy = np.ones(3)

    def cold(Q, B_, passive0=None, coarse=None):
        return solve_exact(Q, B_, passive0=passive0)

    a = solve_edges([G], [B], [[0, 1, 2]], yy, D, ls, lr, steps=3, eps_rel=0.01)
    b = solve_edges([G], [B], [[0, 1, 2]], yy, D, ls, lr, steps=3, eps_rel=0.01, solve=cold)
    assert a.steps == b.steps and np.allclose(a.objective_history, b.objective_history, rtol=1e-10)
    assert np.allclose(a.x, b.x, rtol=1e-8, atol=1e-8 * np.abs(b.x).max())
    assert all(np.all(r.kkt_residual <= KKT_TOL) for r in a.results)
