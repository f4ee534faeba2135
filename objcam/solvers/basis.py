"""Envmap bases of the solves: which unknowns stand for the kept lat-long texels.

A lat-long row holds as many texels as the equator's, but a texel of row r spans ``sin(theta_r)`` times the
equator texel's solid angle: at 32 x 64 the top row's texels are 1/20 of it. The shadows of a diffuse occluder
integrate the light over solid angle, so those slivers are not what the photos resolve; they are unknowns that
only the prior pins down, and every one of them costs the solves (Gram matrices grow with N^2, factorisations
with N^3).

The merged basis with group size ``g`` joins the kept texels of each row into groups of ``k_r`` adjacent
columns, ``k_r`` the largest divisor of the width with ``k_r sin(theta_r) <= g``: no group spans more than g
times the equator texel's solid angle. At 32 x 64, of the 1,088 texels kept above a plane's horizon, g = 1
leaves 868 unknowns (the five rows at the zenith merge 16, 4, 4, 2, 2 texels) and g = sqrt(2) 748 (16, 8, 4, 4,
2, 2, 2, 2); the rows around the horizon stay whole.

The solves minimise the same objective as on the texels, restricted to envmaps ``x = P z`` constant over each
group (P the N x N' 0/1 membership matrix): the data term on the merged columns ``A P``, the smoothness prior on
``D P`` (edges inside a group are zero), the ridge on ``||P z||^2 = sum_g k_g z_g^2``, so the weights keep their
meaning; the result is written back as ``x = P z`` on the lat-long grid. Measured on the bench (bench/results.md,
session 9): see objcam.solvers.plan.defaults.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from objcam.envmap import EnvGrid


def row_group_sizes(grid: EnvGrid, group: float) -> np.ndarray:
    """(H,) columns merged per group in each row: the largest divisor k of the width with k sin(theta) <= group
    (at least 1)."""
    w = grid.width
    divisors = np.array([d for d in range(1, w + 1) if w % d == 0], dtype=np.int64)
    theta = np.pi * (np.arange(grid.height) + 0.5) / grid.height
    limit = group / np.maximum(np.sin(theta), 1e-12) * (1 + 1e-9)
    ok = divisors[None, :] <= limit[:, None]
    return np.where(ok, divisors[None, :], 1).max(axis=1)


def texel_basis(grid: EnvGrid, texel_index: np.ndarray, group: float,
                alone: np.ndarray | None = None) -> sp.csr_matrix | None:
    """(N, N') membership matrix P of the merged basis with group size ``group`` over the kept texels
    ``texel_index`` (full-grid indices, row-major), or None when nothing merges (``group`` < 2 sin of every
    kept row, e.g. 0: one unknown per texel). Groups hold only kept texels and never wrap around the azimuth
    seam; their order follows the texels'. ``alone``: full-grid indices of texels kept out of their groups, each
    its own unknown (a texel whose column is a point source placed by the photo, objcam.transport.points: merged,
    the point would light its whole group)."""
    if not group >= 0:
        raise ValueError(f"texel group size must be >= 0, got {group!r}")
    t = np.asarray(texel_index, dtype=np.int64).ravel()
    if t.size == 0:
        return None
    r, c = t // grid.width, t % grid.width
    k = row_group_sizes(grid, group)[r]
    if np.all(k == 1):
        return None
    key = 2 * (r * grid.width + (c // k) * k)  # the group's first texel; a texel kept alone right after it
    if alone is not None and len(alone):
        own = np.isin(t, np.asarray(alone, np.int64))
        key[own] = 2 * t[own] + 1
    _, gid = np.unique(key, return_inverse=True)
    gid = gid.ravel()
    return sp.csr_matrix((np.ones(t.size), (np.arange(t.size), gid)), shape=(t.size, int(gid.max()) + 1))


#: bytes of G's columns merged at a time by :func:`merge_gram`: below glibc's largest mmap threshold (32 MB), so
#: the freed block's memory serves the next one; a larger block is a fresh mapping each time whose pages fault in
#: (64 MB blocks: 0.97-1.2 CPU s for the 64 x 128 merge in a fresh process, 4 MB: 0.13-0.24 s; bench/results.md,
#: issue 26 session 20)
MERGE_BLOCK_BYTES = 4 * 2**20


def merge_gram(P: sp.spmatrix, G: np.ndarray, block_bytes: int = MERGE_BLOCK_BYTES) -> np.ndarray:
    """``P^T G P`` (N', N') for a symmetric (N, N) G: a Gram or regularised Gram matrix on the merged basis.

    Summed over blocks of G's rows (G may be a memory-mapped file): block b adds ``P_b^T (G_b P)`` to the rows
    of the groups its texels belong to, so beside the result only ~``block_bytes`` of temporaries are held (the
    whole-matrix form held two N x N' products: 4.4 GB at 128 x 256). Exactly symmetric."""
    from objcam.solvers.regularization import _mirror_lower

    P = sp.csr_matrix(P)
    n, k = P.shape
    PT = P.T.tocsr()
    out = np.zeros((k, k))
    rows = max(1, block_bytes // (8 * max(n, 1)))
    for r0 in range(0, n, rows):
        r1 = min(n, r0 + rows)
        Pb = P[r0:r1]
        groups = np.unique(Pb.indices)
        if groups.size == 0:
            continue
        # (G_b P)^T = P^T G[:, b] (G symmetric), from a C-ordered copy of G's columns b (each row's segment: 3x
        # faster than the transposing copy of G_b, and the same numbers for a symmetric G)
        K = PT @ np.ascontiguousarray(G[:, r0:r1], dtype=np.float64)  # (N', b)
        out[groups] += sp.csr_matrix(Pb[:, groups]).T @ K.T
    # each row holds every contribution of its group; rounding differs between (i, j) and (j, i): mirror one
    out = np.ascontiguousarray(out)
    _mirror_lower(out, rows)
    return out


def group_sizes(P: sp.spmatrix) -> np.ndarray:
    """(N',) texels per group: the ridge weights ``diag(P^T P)`` of the merged problem."""
    return np.asarray(sp.csr_matrix(P).sum(axis=0)).ravel()


def unknowns(texel_index: np.ndarray, P: sp.spmatrix | None) -> int:
    """Number of unknowns per envmap channel: the groups of P, else the texels."""
    return int(np.size(texel_index) if P is None else P.shape[1])


def solved_edges(D: sp.spmatrix, P: sp.spmatrix | None) -> sp.csr_matrix:
    """The prior's edges D (E, N) without those that touch a texel outside every group of P (N, N'; a texel
    ``restrict_weak`` excluded): an excluded texel is unsolved, not zero, so no edge may pull its neighbour
    towards 0 (with such edges ``D P`` keeps ``w x_i`` for a solved neighbour i: a ridge that darkened the row
    above the horizon and pushed near-horizon light a row up)."""
    D = sp.csr_matrix(D)
    if P is None:
        return D
    outside = (sp.csr_matrix(P).getnnz(axis=1) == 0).astype(np.float64)
    if not outside.any():
        return D
    touches = np.asarray(abs(D) @ outside).ravel() > 0
    return D[~touches]


def restrict_weak(grid: EnvGrid, texel_index: np.ndarray, P: sp.spmatrix | None, weak: np.ndarray,
                  mode: str) -> sp.csr_matrix | None:
    """The basis P (N, N'; None: one unknown per texel) with the ``weak`` (N,) bool texels held to a stated prior.

    mode 'exclude': weak texels belong to no group (x = P z is 0 there; the solve leaves them unsolved);
    'tie': each weak texel joins the group of the first non-weak kept texel above it in its lat-long column (its
    radiance equals that texel's), left alone when there is none; 'keep': P unchanged.
    Groups left empty are dropped; the others keep their order.
    """
    weak = np.asarray(weak, bool)
    if mode == "keep" or not weak.any():
        return None if P is None else sp.csr_matrix(P)
    t = np.asarray(texel_index, dtype=np.int64).ravel()
    n = t.size
    if P is None:
        gid = np.arange(n)
    else:  # one group per texel: the group of row i
        coo = sp.coo_matrix(P)
        gid = coo.col[np.argsort(coo.row)]
    rows = np.ones(n, bool)
    if mode == "exclude":
        rows = ~weak
    elif mode == "tie":
        pos = {int(v): i for i, v in enumerate(t)}
        order = np.flatnonzero(weak)[np.argsort(t[weak] // grid.width, kind="stable")]  # top rows first
        gid = gid.copy()
        tied = np.zeros(n, bool)
        for i in order:
            r, c = divmod(int(t[i]), grid.width)
            above = pos.get((r - 1) * grid.width + c) if r > 0 else None
            if above is not None and (not weak[above] or tied[above]):
                gid[i], tied[i] = gid[above], True
    else:
        raise ValueError(f"unknown weak-texel mode {mode!r}")
    _, new = np.unique(gid[rows], return_inverse=True)
    keep = np.flatnonzero(rows)
    return sp.csr_matrix((np.ones(keep.size), (keep, new.ravel())), shape=(n, int(new.max()) + 1 if keep.size else 0))
