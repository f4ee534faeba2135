"""A low-rank lower bound of a data Gram matrix, for preconditioning the exact solves (objcam.solvers.nnls).

The exact solves of the reweighted priors (objcam.solvers.edges) see ``Q = G + S`` with G = A^T A dense and the
same at every reweighting step, and S = ls D^T W D + diag(lr) sparse and new at every step. For a diffuse scene
G's spectrum decays fast (64 x 128 forest: the 100th eigenvalue is 3% of G's mean diagonal, the 300th 0.5%), so
``P = S + V diag(lam) V^T`` with G's dominant k eigenpairs follows W exactly and leaves ``Q - P`` small: PCG on a
free block ``Q_FF`` preconditioned by ``P_FF`` (Woodbury: a sparse factorisation of S_FF and a k x k matrix)
needs a handful of iterations where the previous step's factor needed 67-178 (bench/results.md, issue 26).

The pairs come from a randomized Nystrom approximation (Halko, Martinsson & Tropp 2011; the stable form of Tropp,
Yurtsever, Udell & Cevher 2017): ``G_nys = (G O)(O^T G O)^+ (G O)^T`` with O an orthonormal basis of G^q times a
Gaussian matrix. In exact arithmetic ``G - G_nys`` is positive semi-definite, so ``P <= Q`` and the eigenvalues
of ``P^-1 Q`` are >= 1: PCG's error is set by how far G's spectrum beyond k sits above S's.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
from scipy.linalg import cholesky, solve_triangular

#: fewest pairs kept; the rank is sqrt(N) above it (:func:`rank`)
MIN_RANK = 32
#: oversampling and power iterations of the range finder (a fixed seed: the same G gives the same pairs)
OVERSAMPLE = 16
POWER = 2

_cache: dict[int, tuple] = {}
_lock = threading.Lock()
# held while a range finder runs: the luminance and chroma solves (two threads) ask for the same Gram's pairs at
# once, and the second waits for the first's instead of computing them again
_compute = threading.Lock()


def rank(n: int) -> int:
    """The Nystrom rank for N unknowns: sqrt(N), where a preconditioner set-up's |F| k^2 capacitance product
    costs about one N^2 product with Q (a PCG iteration); at least MIN_RANK. At 64 x 128 (3,131 unknowns, k 56)
    that is near the least measured time (k 32 / 64 / 128 / 256: 91 / 62 / 40 / 28 iterations, 1.34 / 0.92 / 0.94
    / 1.08 CPU s on one solve; bench/results.md, issue 26 session 18)."""
    return max(MIN_RANK, int(round(np.sqrt(n))))


def sketch(G: np.ndarray, k: int | None = None, power: int = POWER, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(O (N, m), Y = G O): the range finder's orthonormal test matrix (G^q times a Gaussian one, m = k +
    OVERSAMPLE) and G's product with it, for :func:`from_sketch`. k None: :func:`rank`."""
    n = G.shape[0]
    k = rank(n) if k is None else k
    m = min(n, k + OVERSAMPLE)
    rng = np.random.default_rng(seed)
    Om = np.linalg.qr(rng.standard_normal((n, m)))[0]
    for _ in range(power):  # subspace iteration: the range of G^q O follows the dominant eigenvectors
        Om = np.linalg.qr(G @ Om)[0]
    return Om, G @ Om


def from_sketch(Om: np.ndarray, Y: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(V (N, r), lam (r,)), r <= k: the Nystrom approximation ``Y (O^T Y)^+ Y^T`` of the G with ``Y = G O``,
    a lower bound of G for any orthonormal O (Tropp et al.'s stable form)."""
    n = Om.shape[0]
    # the stable Nystrom form: shift by nu so that O^T Y_nu is safely positive definite, remove it afterwards
    nu = np.sqrt(n) * np.finfo(float).eps * max(float(np.linalg.norm(Y, 2)), 1e-300)
    Ynu = Y + nu * Om
    C = cholesky(Om.T @ Ynu, lower=False, check_finite=False)
    Bm = solve_triangular(C, Ynu.T, trans="T", lower=False, check_finite=False).T  # Y_nu C^-1
    V, sig, _ = np.linalg.svd(Bm, full_matrices=False)
    lam = np.maximum(sig * sig - nu, 0.0)
    r = min(k, int(np.count_nonzero(lam > 0)))
    return np.ascontiguousarray(V[:, :r]), lam[:r].copy()


def nystrom(G: np.ndarray, k: int | None = None, power: int = POWER, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(V (N, r), lam (r,)): ``V diag(lam) V^T`` a rank-r (r <= k) Nystrom approximation of the symmetric PSD G
    (N, N) from below, V orthonormal, lam >= 0 descending; k None: :func:`rank`. Cost ~2 (power + 1) N^2 (k + OVERSAMPLE) flops."""
    k = rank(G.shape[0]) if k is None else k
    return from_sketch(*sketch(G, k, power, seed), k)


def _store(G: np.ndarray, k: int | None, out: tuple, sk: tuple) -> None:
    key = id(G)
    with _lock:
        try:
            ref = weakref.ref(G, lambda _r, key=key: _cache.pop(key, None))
        except TypeError:  # not weak-referenceable: no caching
            return
        _cache[key] = (ref, k, out, sk)


def _cached(G: np.ndarray, k: int | None):
    with _lock:
        hit = _cache.get(id(G))
        return hit if hit is not None and hit[0]() is G and hit[1] == k else None


def gram_lowrank(G: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`nystrom` of G, computed once per array object (the luminance and chroma solves and every reweighting
    step share one merged Gram); the entry is dropped with the array."""
    hit = _cached(G, k)
    if hit is not None:
        return hit[2]
    with _compute:
        hit = _cached(G, k)  # (made by another thread meanwhile)
        if hit is not None:
            return hit[2]
        kk = rank(G.shape[0]) if k is None else k
        sk = sketch(G, kk)
        out = from_sketch(*sk, kk)
        _store(G, k, out, sk)
    return out


def lowrank_update(G_new: np.ndarray, G: np.ndarray, U: np.ndarray, w: np.ndarray) -> bool:
    """Cache the pairs of ``G_new = G - U diag(w) U^T`` (U (N, r), a few rows of A dropped or down-weighted:
    objcam.solvers.plan.known.downdated) for :func:`gram_lowrank`, from G's cached sketch: the same test matrix
    O with ``G_new O = G O - U (w (U^T O))`` (N r m flops instead of a new range finder's 2 (q + 1) N^2 m).
    The Nystrom form is a lower bound of G_new for any orthonormal O; O follows G's dominant subspace, which r
    rows barely move. False (nothing cached) when G has no cached sketch."""
    for k in {None, rank(G.shape[0])}:
        hit = _cached(G, k)
        if hit is None or hit[3] is None:
            continue
        Om, Y = hit[3]
        Y_new = Y - U @ (np.asarray(w, dtype=np.float64)[:, None] * (U.T @ Om))
        kk = rank(G.shape[0]) if k is None else k
        try:
            out = from_sketch(Om, Y_new, kk)
        except np.linalg.LinAlgError:  # (G_new not numerically PSD on O: left to a fresh range finder)
            return False
        _store(G_new, k, out, (Om, Y_new))
        return True
    return False
