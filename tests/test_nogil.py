"""objcam.solvers.nogil: LAPACK's Cholesky and triangular solves through ctypes, the same numbers as scipy's
wrappers, with the GIL released."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve, lapack, solve_triangular

from objcam.solvers import nogil


def _spd(n: int, seed: int = 0) -> np.ndarray:
    A = np.random.default_rng(seed).standard_normal((n, n))
    S = A @ A.T + n * np.eye(n)
    return 0.5 * (S + S.T)


@pytest.mark.parametrize("n", [1, 7, 300])
def test_the_same_numbers_as_scipys_wrappers(n):
    rng = np.random.default_rng(n)
    S = _spd(n, n)
    c1, i1 = lapack.dpotrf(S.T, lower=0, clean=1)
    c2, i2 = nogil.potrf(S.T)
    assert i1 == i2 == 0 and c2.flags.f_contiguous and np.array_equal(c1, c2)
    assert np.array_equal(np.tril(c2, -1), np.zeros((n, n)))  # clean: the strict lower triangle zeroed
    # a C-ordered, not exactly symmetric matrix: LAPACK sees the logical matrix (its upper triangle), as in scipy
    Sn = S + 1e-9 * rng.standard_normal(S.shape)
    assert np.array_equal(lapack.dpotrf(Sn.copy(), lower=0, clean=1, overwrite_a=1)[0],
                          nogil.potrf(Sn.copy(), overwrite=True)[0])
    assert n == 1 or not np.array_equal(nogil.potrf(Sn)[0], nogil.potrf(Sn.T)[0])  # (the premise: it matters)
    B = rng.standard_normal((n, 3))
    assert np.array_equal(lapack.dpotrs(c1, B, lower=0)[0], nogil.potrs(c2, B)[0])
    assert np.array_equal(lapack.dpotrs(c1, B[:, 1], lower=0)[0], nogil.potrs(c2, B[:, 1])[0])
    for U in (c1, np.ascontiguousarray(c1)):  # Fortran- and C-ordered factors
        for tr in (False, True):
            ref = solve_triangular(U, B, trans="T" if tr else "N", lower=False, check_finite=False)
            assert np.array_equal(ref, nogil.trtrs(U, B, trans=tr))
    assert np.array_equal(cho_solve(cho_factor(S, check_finite=False), B, check_finite=False),
                          nogil.cho_solve(nogil.cho_factor(S), B))
    # in place when asked and possible: the factor is the argument's memory
    F = np.asfortranarray(S)
    assert nogil.potrf(F, overwrite=True)[0] is F and np.array_equal(F, c1)


def test_failures_are_reported():
    assert nogil.potrf(-np.eye(4))[1] == 1
    with pytest.raises(np.linalg.LinAlgError):
        nogil.cho_factor(np.diag([1.0, -1.0, 1.0]))
    U = np.triu(np.ones((3, 3)), 0)
    U[1, 1] = 0.0
    with pytest.raises(np.linalg.LinAlgError):
        nogil.trtrs(np.asfortranarray(U), np.ones(3))


def test_the_calls_release_the_gil():
    # ctypes releases the GIL for functions of CFUNCTYPE, not for those flagged as Python API calls
    for name, nargs in (("dpotrf", 5), ("dpotrs", 8), ("dtrtrs", 10)):
        assert not nogil._fn(name, nargs)._flags_ & ctypes._FUNCFLAG_PYTHONAPI
    assert not nogil._fn("dsymv", 10, blas=True)._flags_ & ctypes._FUNCFLAG_PYTHONAPI


def test_symv_is_blas_dsymv():
    """nogil.symv: the numbers of scipy's dsymv wrapper (the same routine), column by column."""
    from scipy.linalg import blas

    S = _spd(200, 3)
    V = np.random.default_rng(1).standard_normal((200, 3))
    got = nogil.symv(S, V)
    for j in range(3):
        assert np.array_equal(got[:, j], blas.dsymv(1.0, S.T, V[:, j], lower=1))
