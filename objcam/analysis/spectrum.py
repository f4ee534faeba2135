"""Singular spectrum of the light-transport matrix and its effective rank.

:func:`singular_spectrum` takes the eigenvalues of the smaller Gram matrix (``A^T A``, or ``A A^T`` when
M < N) in float64 -- much cheaper than an SVD of a tall A. Squaring costs relative accuracy below
``~sqrt(eps) * s_0 ~ 1.5e-8 s_0``: singular values smaller than that come out as noise of that size (or 0),
which is far below any threshold used here.

Effective rank, two definitions:

- :func:`effective_rank`: the number of singular values above ``tol * s_0`` (default ``tol = 1e-3``: modes
  attenuated more than 1000x relative to the strongest are counted as not recovered). An A with two identical
  columns has exactly one fewer.
- :func:`entropy_effective_rank` (Roy & Vetterli 2007): ``exp(H(p))`` with ``p_k = s_k / sum s`` and
  ``H = -sum p_k log p_k`` -- a real number in [1, min(M, N)], no threshold.

:func:`ridge_dof` gives ``sum s_k^2 / (s_k^2 + lr)``, the effective number of parameters of the ridge fit
(equal to the trace of the hat matrix, i.e. the sum of the leverages).
"""

from __future__ import annotations

import numpy as np

from objcam.analysis.leverage import _check_A, _gram
from objcam.threads import single_blas_thread

DEFAULT_RANK_TOL = 1e-3


def singular_spectrum(A: np.ndarray, *, G: np.ndarray | None = None) -> np.ndarray:
    """Singular values of ``A`` (M, N), descending, (min(M, N),) float64, from ``eigvalsh`` of the smaller
    Gram matrix. Pass ``G = A^T A`` to reuse it (then the result still has min(M, N) entries)."""
    A = _check_A(A)
    m, n = A.shape
    with single_blas_thread():
        if G is None:
            G = _gram(A) if m >= n else _gram(A.T)
        ev = np.linalg.eigvalsh(np.asarray(G, dtype=np.float64))
    sv = np.sqrt(np.clip(ev[::-1], 0.0, None))
    return sv[: min(m, n)]


def effective_rank(sv: np.ndarray, tol: float = DEFAULT_RANK_TOL) -> int:
    """Number of singular values ``> tol * sv.max()`` (0 for an all-zero spectrum)."""
    sv = np.asarray(sv, dtype=np.float64)
    top = float(sv.max()) if sv.size else 0.0
    if top <= 0:
        return 0
    return int(np.count_nonzero(sv > tol * top))


def entropy_effective_rank(sv: np.ndarray) -> float:
    """Roy & Vetterli's effective rank ``exp(-sum p_k log p_k)``, ``p_k = s_k / sum(s)`` (0 log 0 = 0)."""
    sv = np.clip(np.asarray(sv, dtype=np.float64), 0.0, None)
    tot = float(sv.sum())
    if tot <= 0:
        return 0.0
    p = sv[sv > 0] / tot
    return float(np.exp(-np.sum(p * np.log(p))))


def ridge_dof(sv: np.ndarray, lr: float) -> float:
    """``sum s_k^2 / (s_k^2 + lr)`` (absolute ``lr``): the trace of the ridge hat matrix."""
    s2 = np.asarray(sv, dtype=np.float64) ** 2
    if lr <= 0:
        return float(np.count_nonzero(s2 > 0))
    return float(np.sum(s2 / (s2 + lr)))
