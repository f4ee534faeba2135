"""Free blocks solved from an earlier block's Cholesky factor (objcam.solvers.blockchol.UpdatedFree): the same block
solutions and the same exact minimiser as fresh factorisations, with fewer of them."""

from __future__ import annotations

import numpy as np
import pytest

import objcam.solvers.blockchol as blockchol
import objcam.solvers.nnls as nnls
from objcam.solvers import solve_exact
from tests.test_pcg_free import _problem

CLOSE = 1e-9  # a block solution against a fresh factorisation's, relative to its max |x| (both refined once)
KKT_TOL = 1e-8


@pytest.fixture(scope="module")
def prob():
    D, Q, B, G, S, ls, lr = _problem(seed=5)
    return Q, B


def _updated(Q, B, stats):
    return blockchol.UpdatedFree(Q, B, stats, lambda F, g, X, G, fac=None: nnls._solve_free(Q, B, F, g, X, G, stats,
                                                                                          fac=fac))


def _fresh(Q, B, F, cols):
    X, G = np.zeros(B.shape), np.zeros(B.shape)
    nnls._solve_free(Q, B, F, cols, X, G, nnls._Stats())
    return X, G


def _close(x: np.ndarray, ref: np.ndarray) -> bool:
    return bool(np.abs(x - ref).max() <= CLOSE * np.abs(ref).max())


def test_updated_blocks_equal_fresh_factorisations(prob):
    Q, B = prob
    n = Q.shape[0]
    rng = np.random.default_rng(0)
    F = np.zeros((n, 3), dtype=bool)
    F[:, 0] = rng.random(n) < 0.5  # the first round: column 0's block factorised afresh
    stats = nnls._Stats()
    upd = _updated(Q, B, stats)
    X, G = np.zeros(B.shape), np.zeros(B.shape)
    upd(F, [0], X, G)
    assert stats.factorizations == 1 and stats.chol_updates == 0
    # the next round: 15 variables leave column 0's free set and 15 enter; columns 1 and 2 differ from it by a few
    F0 = F[:, 0].copy()
    on, off = np.flatnonzero(F0), np.flatnonzero(~F0)
    F[rng.choice(on, 15, replace=False), 0] = False
    F[rng.choice(off, 15, replace=False), 0] = True
    F[:, 1] = F0
    F[rng.choice(off, 5, replace=False), 1] = True
    F[:, 2] = F[:, 0]
    F[rng.choice(np.flatnonzero(F[:, 0]), 4, replace=False), 2] = False
    upd(F, [0, 1, 2], X, G)
    assert stats.factorizations == 1 and stats.chol_updates == 3  # no new factorisation
    Xr, Gr = _fresh(Q, B, F, [0, 1, 2])
    assert np.all(X[~F] == 0.0)
    assert _close(X, Xr) and _close(G, Gr)
    # broken: the bordered factor solved without holding the removed variables at zero
    S = np.flatnonzero(F0 | F[:, 0])
    xb = np.zeros(n)
    xb[S] = np.linalg.solve(Q[np.ix_(S, S)], B[S, 0])
    assert not _close(xb[:, None], Xr[:, :1])


def test_far_sets_are_factorised_afresh(prob):
    Q, B = prob
    n = Q.shape[0]
    rng = np.random.default_rng(1)
    F = (rng.random((n, 1)) < 0.5)
    stats = nnls._Stats()
    upd = _updated(Q, B, stats)
    X, G = np.zeros(B.shape), np.zeros(B.shape)
    upd(F, [0], X, G)
    X0 = X.copy()
    F = ~F  # nothing in common: an update would cost more than a factorisation
    upd(F, [0], X, G)
    assert stats.factorizations == 2 and stats.chol_updates == 0
    ref = _fresh(Q, B, F, [0])[0][:, :1]
    assert _close(X[:, :1], ref)
    assert not _close(X0[:, :1], ref)  # broken: the previous set's solution


def test_solve_with_updates_reaches_the_same_minimiser(prob, monkeypatch):
    Q, B = prob
    r = solve_exact(Q, B, schur=True)
    monkeypatch.setattr(blockchol, "CHOL_UPDATE_SHARE", 0.0)  # main's path: a fresh factorisation per block
    ref = solve_exact(Q, B, schur=True)
    assert r.converged and np.all(r.kkt_residual <= KKT_TOL) and np.all(ref.kkt_residual <= KKT_TOL)
    assert r.info["chol_updates"] > 0 and ref.info["chol_updates"] == 0
    assert r.info["factorizations"] < ref.info["factorizations"]
    assert np.array_equal(r.x > 0, ref.x > 0) and _close(r.x, ref.x)
    assert np.allclose(r.objective, ref.objective, rtol=1e-12)
    # broken: a loose pivoting tolerance stops short of the minimiser
    loose = solve_exact(Q, B, schur=True, tol=1e-3)
    assert not (np.array_equal(loose.x > 0, ref.x > 0) and _close(loose.x, ref.x))


def test_an_indefinite_schur_complement_falls_back_to_a_fresh_factor(prob, monkeypatch):
    Q, B = prob
    n = Q.shape[0]
    rng = np.random.default_rng(2)
    F = rng.random((n, 1)) < 0.5
    stats = nnls._Stats()
    upd = _updated(Q, B, stats)
    X, G = np.zeros(B.shape), np.zeros(B.shape)
    upd(F, [0], X, G)
    X0 = X.copy()
    F[rng.choice(np.flatnonzero(F[:, 0]), 5, replace=False), 0] = False

    def fail(*a, **k):
        raise np.linalg.LinAlgError("not definite")

    monkeypatch.setattr("objcam.solvers.nogil.cho_factor", fail)
    upd(F, [0], X, G)
    assert stats.factorizations == 2 and stats.chol_updates == 0
    ref = _fresh(Q, B, F, [0])[0][:, :1]
    assert _close(X[:, :1], ref) and not _close(X0[:, :1], ref)  # broken: the previous set's solution
