"""The memory-lean Gram pieces behind a 128 x 256 solve (issue 26): the blocked syrk Gram, gram.npy streamed per
channel and memory-mapped, merge_gram over row blocks, regularized_gram into a reused buffer, and one merged Gram
shared by the edge solves. Each is checked against the plain dense formula it replaces, on a small A."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from objcam.envmap import EnvGrid
from objcam.solvers import difference_operator, gram, regularized_gram
from objcam.solvers.basis import merge_gram, texel_basis
from objcam.solvers.edges import solve_edges


def _A(m: int = 700, n: int = 300, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.random((m, n)) * (rng.random((m, n)) < 0.3)).astype(np.float32)


def test_blocked_syrk_gram_is_the_exact_symmetric_product_and_fills_a_given_buffer(tmp_path):
    A = _A()
    ref = A.astype(np.float64).T @ A.astype(np.float64)
    G = gram(A)
    assert G.flags.c_contiguous and np.array_equal(G, G.T)
    assert np.abs(G - ref).max() <= 1e-13 * np.abs(ref).max()
    # into a memory-mapped file, over many row blocks (a block of 7 rows: the mirror's block loop runs too)
    import objcam.solvers.regularization as reg

    old = reg._GRAM_BLOCK_BYTES
    reg._GRAM_BLOCK_BYTES = 7 * 8 * A.shape[1]
    try:
        mm = np.lib.format.open_memmap(tmp_path / "g.npy", mode="w+", dtype=np.float64, shape=ref.shape)
        mm[...] = 5.0  # stale contents are overwritten, not added to
        out = gram(A, out=mm)
        assert out is mm and np.array_equal(np.asarray(mm), np.asarray(mm).T)
        assert np.abs(mm - ref).max() <= 1e-13 * np.abs(ref).max()
    finally:
        reg._GRAM_BLOCK_BYTES = old


def test_write_gram_streams_every_channel_and_the_transport_maps_it_read_only(tmp_path):
    from objcam.transport.storage import GRAM, Transport, write_gram

    A = np.stack([_A(seed=s) for s in range(3)])  # (3, M, N): an albedo per channel

    class _Fake:  # what write_gram reads of the group: A and its shape
        def __init__(self, A):
            self.A, self.channels, self.n_texels = A, A.shape[0], A.shape[2]

    import objcam.transport.storage as st

    real = st.load_group
    st.load_group = lambda folder, load_A=True: _Fake(A)
    try:
        write_gram(tmp_path)
    finally:
        st.load_group = real
    G = np.load(tmp_path / GRAM)
    assert G.shape == (3, 300, 300) and G.dtype == np.float64
    for c in range(3):
        ref = A[c].astype(np.float64).T @ A[c].astype(np.float64)
        assert np.abs(G[c] - ref).max() <= 1e-13 * np.abs(ref).max()
    assert [p.name for p in tmp_path.iterdir()] == [GRAM]  # no temporary left behind
    # Transport.gram(): the file memory-mapped, read-only, the same object each time
    T = Transport.__new__(Transport)
    T.folder, T._gram = tmp_path, None
    M = T.gram()
    assert isinstance(M, np.memmap) and not M.flags.writeable and M is T.gram()
    assert np.array_equal(np.asarray(M), G)


def test_merge_gram_by_row_blocks_equals_the_dense_product_for_any_basis():
    grid = EnvGrid(16)
    t = np.arange((grid.height // 2 + 1) * grid.width)
    P = texel_basis(grid, t, 1.5)
    # a generic basis too: a texel left out (a weak texel excluded) and one tied to a group of another row
    L = P.tolil()
    L[5, :] = 0
    L[40, :] = 0
    L[40, 3] = 1
    rng = np.random.default_rng(1)
    X = rng.random((400, t.size))
    G = X.T @ X
    for B in (P, sp.csr_matrix(L)):
        Pd = B.toarray()
        ref = Pd.T @ G @ Pd
        for block in (8 * t.size * 5, 64 * 2**20):  # five rows per block, and one block
            M = merge_gram(B, G, block_bytes=block)
            assert np.array_equal(M, M.T)
            assert np.abs(M - ref).max() <= 1e-13 * np.abs(ref).max()


def test_regularized_gram_into_a_reused_buffer_and_a_shared_merged_gram_give_the_same_solve():
    grid = EnvGrid(8)
    t = np.arange((grid.height // 2 + 1) * grid.width)
    A = _A(400, t.size, seed=3).astype(np.float64)
    G = A.T @ A
    D = difference_operator(grid, t)
    buf = np.full_like(G, 7.0)
    Q = regularized_gram(G, D, 0.3, 1e-3, out=buf)
    assert Q is buf and np.array_equal(Q, regularized_gram(G, D, 0.3, 1e-3))
    # the edge solve given the merged Gram (merged=True) is the solve that merges it itself
    x_true = np.abs(np.sin(np.arange(t.size)))
    y = A @ x_true
    B = (A.T @ y)[:, None]
    P = texel_basis(grid, t, 1.5)
    args = ([0, 1, 2],), np.array([y @ y] * 3), D
    a = solve_edges([G], [np.repeat(B, 3, axis=1)], *args, 1e-2 * np.mean(np.diag(G)), 1e-6, steps=3, basis=P)
    b = solve_edges([merge_gram(P, G)], [np.asarray(P.T @ np.repeat(B, 3, axis=1))], *args,
                    1e-2 * np.mean(np.diag(G)), 1e-6, steps=3, basis=P, merged=True)
    assert np.array_equal(a.x, b.x) and a.objective_history == b.objective_history
    assert a.x.max() > 0 and max(float(r.kkt_residual.max()) for r in a.results) < 1e-8  # exact, not zeros
