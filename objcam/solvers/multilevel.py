"""Coarse-to-fine warm starts for the exact non-negative solves (objcam.solvers.nnls).

Block principal pivoting started cold takes the unconstrained solution as its first free set. On an envmap most
of whose texels end at 0 (the edge prior's solves at 64 x 128 end with ~2/3 of the unknowns at 0) that first
guess is far from the answer: the cold solve needed 9 rounds and 22 factorisations of free blocks, one of them
of the whole matrix. The same objective restricted to envmaps constant over aggregates of ~4 neighbouring
unknowns (``x = P_c z``: Gram ``P_c^T Q P_c``, right-hand side ``P_c^T b``) has a quarter of the unknowns; its
exact solution, prolonged, is a free set close to the fine one: the fine solve from it took 4 rounds and 12
factorisations, and (being exact) reaches the same minimiser (bench/results.md, "Issue 26").

The aggregates come from the prior's own graph (the rows of D join neighbouring unknowns): two rounds of greedy
pairwise matching, so they follow the texel groups of objcam.solvers.basis and whatever texels were kept,
without knowing the grid.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from objcam.solvers.basis import merge_gram

#: fewest unknowns for which a coarse warm start pays: below it one cold factorisation is cheap
MIN_UNKNOWNS = 256


def _match(adj: sp.csr_matrix) -> sp.csr_matrix:
    """(n, n') 0/1 aggregation joining each unknown with at most one unmatched neighbour in ``adj`` (greedy, in
    index order; unknowns without an unmatched neighbour stay alone)."""
    n = adj.shape[0]
    agg = np.full(n, -1, dtype=np.int64)
    k = 0
    ptr, ind = adj.indptr, adj.indices
    for i in range(n):
        if agg[i] >= 0:
            continue
        agg[i] = k
        nb = ind[ptr[i]:ptr[i + 1]]
        free = nb[agg[nb] < 0]
        if free.size:
            agg[free[0]] = k
        k += 1
    return sp.csr_matrix((np.ones(n), (np.arange(n), agg)), shape=(n, k))


def aggregates(D: sp.spmatrix, levels: int = 2) -> sp.csr_matrix:
    """(n, n_c) 0/1 matrix P_c of aggregates of up to ``2**levels`` unknowns joined by the rows of D (E, n)."""
    D = sp.csr_matrix(D)
    P = sp.identity(D.shape[1], format="csr")
    for _ in range(levels):
        Dl = sp.csr_matrix(D @ P)
        adj = (abs(Dl).T @ abs(Dl)).tocsr()
        adj.setdiag(0)
        adj.eliminate_zeros()
        P = sp.csr_matrix(P @ _match(adj))
    return P


def coarse_passive(Q: np.ndarray, B: np.ndarray, Pc: sp.spmatrix, solve) -> np.ndarray:
    """(n, C) bool: the free set (x > 0) of the exact solution of the objective restricted to ``x = P_c z``.

    Q (n, n), B (n, C) as for objcam.solvers.nnls.solve_exact; ``solve(Qc, Bc)`` the exact solver to use on the
    coarse problem (passed in: this module is imported by objcam.solvers.nnls)."""
    Pc = sp.csr_matrix(Pc)
    B2 = B.reshape(B.shape[0], -1)
    if hasattr(Q, "S"):  # objcam.solvers.products.GramPlusSparse: P^T (G + S) P
        Qc = merge_gram(Pc, Q.G)
        Qc += (Pc.T @ Q.S @ Pc).toarray()
    else:
        Qc = merge_gram(Pc, Q)
    res = solve(Qc, np.asarray(Pc.T @ B2))
    return np.asarray(Pc @ res.x) > 0
