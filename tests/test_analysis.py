"""objcam.analysis: leverage, Cook's distance, texel uncertainty, gain images and the singular spectrum against
dense references, their properties, a geometric toy, plots and a timing bound."""

from __future__ import annotations

import time

import numpy as np
import pytest

from objcam.analysis import (
    absolute_ridge,
    column_scale,
    cooks_distance,
    effective_rank,
    entropy_effective_rank,
    gain_images,
    leverage,
    plot_envmap_map,
    plot_image_grid,
    plot_image_map,
    plot_spectrum,
    regularizer,
    ridge_cholesky,
    ridge_dof,
    scatter_to_image,
    singular_spectrum,
    texel_columns,
    texel_uncertainty,
    to_grid,
)
from objcam.envmap import EnvGrid
from objcam.solvers import difference_operator, gram


def small_case(m=300, n=40, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.random((m, n)) * (rng.random((m, n)) < 0.6)
    A[:, 3] += 0.9 * A[:, 4]  # some correlation between columns
    y = A @ rng.random(n) + 0.05 * rng.standard_normal(m)
    lr = absolute_ridge(A, 1e-2)
    return A, y, lr


def dense_Q(A, lr):
    return A.T @ A + lr * np.eye(A.shape[1])


# --- dense references -------------------------------------------------------------------------------------------

def test_leverage_matches_dense_hat_matrix():
    A, _, lr = small_case()
    H = A @ np.linalg.solve(dense_Q(A, lr), A.T)
    h = leverage(A, lr, block_bytes=8 * 40 * 37)  # 37-row blocks: exercises the blocking, incl. a ragged last one
    np.testing.assert_allclose(h, np.diag(H), rtol=1e-6)
    np.testing.assert_allclose(leverage(A, lr), np.diag(H), rtol=1e-6)
    # float32 A: computed in float64 from the float32 values
    A32 = A.astype(np.float32)
    H32 = A32.astype(np.float64) @ np.linalg.solve(dense_Q(A32.astype(np.float64), lr), A32.T.astype(np.float64))
    np.testing.assert_allclose(leverage(A32, lr), np.diag(H32), rtol=1e-6)


def test_uncertainty_matches_dense_inverse():
    A, _, lr = small_case()
    ref = np.sqrt(np.diag(np.linalg.inv(dense_Q(A, lr))))
    np.testing.assert_allclose(texel_uncertainty(A, lr), ref, rtol=1e-9)
    L = ridge_cholesky(A, lr)
    np.testing.assert_allclose(texel_uncertainty(None, lr, L=L, sigma=0.5), 0.5 * ref, rtol=1e-9)
    np.testing.assert_allclose(texel_uncertainty(None, lr, G=A.T @ A), ref, rtol=1e-9)


def test_gain_rows_match_dense():
    A, _, _ = small_case()
    grid = EnvGrid(4)  # 4 x 8 = 32 texels; keep 20 of them as the columns of a 20-column A
    texel_index = np.sort(np.random.default_rng(1).choice(grid.n_texels, 20, replace=False))
    A = A[:, :20]
    G = gram(A)
    ls, lr = 0.3 * np.mean(np.diag(G)), 1e-2 * np.mean(np.diag(G))
    R = regularizer(grid, texel_index, ls, lr)
    D = difference_operator(grid, texel_index).toarray()
    R_dense = ls * D.T @ D + lr * np.eye(20)
    np.testing.assert_allclose(R.toarray(), R_dense, rtol=1e-12, atol=1e-12)
    full = np.linalg.inv(A.T @ A + R_dense) @ A.T
    rows = [0, 7, 19, 7]
    np.testing.assert_allclose(gain_images(A, R, rows), full[rows], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(gain_images(A, R_dense, rows, G=G), full[rows], rtol=1e-8, atol=1e-12)
    # scalar R = ridge only
    ridge = np.linalg.inv(A.T @ A + lr * np.eye(20)) @ A.T
    np.testing.assert_allclose(gain_images(A, lr, [2]), ridge[[2]], rtol=1e-8, atol=1e-12)
    # texel_columns maps grid texels to columns
    assert texel_columns(texel_index, texel_index[[5, 2]]).tolist() == [5, 2]
    with pytest.raises(ValueError):
        texel_columns(texel_index, np.setdiff1d(np.arange(grid.n_texels), texel_index)[:1])


def test_cooks_distance_matches_dense_formula():
    A, y, lr = small_case()
    Q = dense_Q(A, lr)
    H = A @ np.linalg.solve(Q, A.T)
    x = np.linalg.solve(Q, A.T @ y)
    e = y - A @ x
    h = np.diag(H)
    p = np.trace(H)
    s2 = e @ e / (len(y) - p)
    ref = e**2 / (p * s2) * h / (1 - h) ** 2
    np.testing.assert_allclose(cooks_distance(A, y, x, lr), ref, rtol=1e-8)
    # per channel: (M, C) in, (M, C) out, each channel its own s^2
    Y = np.stack([y, 2 * y + 0.1], axis=1)
    X = np.linalg.solve(Q, A.T @ Y)
    Dc = cooks_distance(A, Y, X, lr, h=h)
    assert Dc.shape == (len(y), 2)
    np.testing.assert_allclose(Dc[:, 0], ref, rtol=1e-8)


def test_cooks_distance_is_the_deletion_definition_for_ols():
    """lr = 0: D_i = ||A x - A x_(i)||^2 / (p s^2) with x_(i) refitted without pixel i (the textbook definition)."""
    A, y, _ = small_case(m=120, n=10, seed=3)
    m, n = A.shape
    x = np.linalg.lstsq(A, y, rcond=None)[0]
    e = y - A @ x
    s2 = e @ e / (m - n)
    ref = np.empty(m)
    for i in range(m):
        keep = np.arange(m) != i
        xi = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        ref[i] = np.sum((A @ x - A @ xi) ** 2) / (n * s2)
    np.testing.assert_allclose(cooks_distance(A, y, x, 0.0), ref, rtol=1e-7)


# --- properties -----------------------------------------------------------------------------------------------

def test_leverage_properties():
    A, _, lr = small_case()
    h = leverage(A, lr)
    assert np.all(h >= 0) and np.all(h < 1)
    H = A @ np.linalg.solve(dense_Q(A, lr), A.T)
    s = np.linalg.svd(A, compute_uv=False)
    np.testing.assert_allclose(h.sum(), np.trace(H), rtol=1e-9)
    np.testing.assert_allclose(h.sum(), np.sum(s**2 / (s**2 + lr)), rtol=1e-9)
    np.testing.assert_allclose(ridge_dof(singular_spectrum(A), lr), h.sum(), rtol=1e-9)
    # the inputs are left alone, a zero row has no leverage
    A_before = A.copy()
    leverage(A, lr)
    leverage(A, lr, block_bytes=8 * 40 * 7)
    np.testing.assert_array_equal(A, A_before)
    A0 = A.copy()
    A0[5] = 0
    assert leverage(A0, lr)[5] == 0


def test_uncertainty_shrinks_with_more_ridge_and_more_data():
    A, _, lr = small_case()
    u = texel_uncertainty(A, lr)
    assert np.all(texel_uncertainty(A, 10 * lr) < u)
    assert np.all(texel_uncertainty(np.vstack([A, A]), lr) < u)
    assert np.all(u <= 1 / np.sqrt(lr) + 1e-12)


def test_relative_ridge_and_rank_deficiency():
    A, _, _ = small_case()
    np.testing.assert_allclose(column_scale(A), np.mean(np.diag(A.T @ A)), rtol=1e-12)
    np.testing.assert_allclose(absolute_ridge(None, 1e-3, G=A.T @ A), 1e-3 * np.mean(np.diag(A.T @ A)), rtol=1e-12)
    B = np.hstack([A, A[:, :1]])  # duplicated column: singular without a ridge
    with pytest.raises(ValueError, match="positive definite"):
        leverage(B, 0.0)
    assert np.all(np.isfinite(texel_uncertainty(B, 1e-6)))


def test_spectrum_matches_svd_and_rank():
    A, _, _ = small_case()
    ref = np.linalg.svd(A, compute_uv=False)
    sv = singular_spectrum(A)
    assert sv.shape == (40,)
    np.testing.assert_allclose(sv, ref, rtol=1e-8, atol=1e-10 * ref[0])
    wide = A[:25].T  # M < N: through A A^T, still min(M, N) values
    np.testing.assert_allclose(singular_spectrum(wide), np.linalg.svd(wide, compute_uv=False), rtol=1e-8)
    B = A.copy()
    B[:, 10] = B[:, 20]  # two identical columns
    svb = singular_spectrum(B)
    assert effective_rank(sv, 1e-6) == 40
    assert effective_rank(svb, 1e-6) == 39
    assert entropy_effective_rank(svb) < entropy_effective_rank(sv)
    # entropy rank: n for a flat spectrum, 1 for a single mode
    assert entropy_effective_rank(np.ones(7)) == pytest.approx(7.0)
    assert entropy_effective_rank(np.array([3.0, 0, 0])) == pytest.approx(1.0)
    assert effective_rank(np.zeros(3)) == 0


def test_layout_helpers():
    grid = EnvGrid(4)
    idx = np.array([0, 9, 31])
    g = to_grid(np.array([1.0, 2.0, 3.0]), grid, idx)
    assert g.shape == (4, 8) and g[0, 0] == 1 and g[1, 1] == 2 and g[3, 7] == 3
    assert np.isnan(g).sum() == 29
    g3 = to_grid(np.ones((3, 3)), grid, idx, fill=0.0)
    assert g3.shape == (4, 8, 3) and g3.sum() == 9
    im = scatter_to_image(np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([1, 5]), (2, 3))
    assert im.shape == (2, 2, 3) and im[0, 0, 1] == 1 and im[1, 1, 2] == 4 and np.isnan(im).sum() == 8


# --- a geometric toy --------------------------------------------------------------------------------------------

def sphere_shadow_transport(height=8, side=24, radius=0.25, centre_z=0.9):
    """A ground plane [-1, 1]^2 (side x side pixels, normal +z, unit albedo) under an occluding sphere, lit by the
    upper hemisphere of a ``height`` x 2 ``height`` envmap. A[i, j] = visibility * cos * solid angle, averaged
    over 16 directions per texel. Returns grid, kept texel indices (N,), A (M, N)."""
    grid = EnvGrid(height)
    rows, cols = np.divmod(np.arange(grid.n_texels), grid.width)
    keep = rows < height // 2  # upper hemisphere
    texel_index = np.flatnonzero(keep)
    u = (np.arange(4) + 0.5) / 4
    uu, vv = (a.ravel() for a in np.meshgrid(u, u))
    d = grid.sample_in_texels(uu[:, None], vv[:, None], rows[keep][None], cols[keep][None])  # (16, N, 3)
    xs = (np.arange(side) + 0.5) / side * 2 - 1
    px, py = np.meshgrid(xs, xs, indexing="ij")
    p = np.stack([px.ravel(), py.ravel(), np.zeros(px.size)], axis=1)  # (M, 3)
    c = np.array([0.0, 0.0, centre_z])
    oc = p - c  # ray p + t d hits the sphere iff b^2 - (|oc|^2 - r^2) > 0 with b = oc.d and t > 0
    b = np.einsum("mk,snk->smn", oc, d)
    disc = b**2 - (np.sum(oc**2, axis=1)[None, :, None] - radius**2)
    hit = (disc > 0) & (-b - np.sqrt(np.clip(disc, 0, None)) > 0)
    cos = np.clip(d[..., 2], 0, None)[:, None, :]
    omega = grid.solid_angles().ravel()[texel_index]
    A = np.mean(np.where(hit, 0.0, cos), axis=0) * omega[None, :]
    return grid, texel_index, A


def test_near_horizon_texels_are_least_certain():
    """With the sphere 0.9 above the plane, texels within 22.5 deg of the horizon cast their shadows off the
    plane: their columns are all the same unshadowed cosine pattern (collinear), so the shadows cannot tell
    them apart, while higher texels cast distinct shadows. With unit-norm columns (so only collinearity, not
    brightness, matters) the horizon row is far less certain than every other row, close to the ridge bound
    1 / sqrt(lr)."""
    grid, texel_index, A = sphere_shadow_transport()
    An = A / np.linalg.norm(A, axis=0)
    horizon = texel_index // grid.width == grid.height // 2 - 1
    cosines = An[:, horizon].T @ An[:, horizon]
    assert cosines.min() > 0.999  # nearly collinear
    lr = absolute_ridge(An, 1e-4)
    u = texel_uncertainty(An, lr)
    assert u[horizon].min() > 3 * u[~horizon].max()
    assert u[horizon].max() <= 1 / np.sqrt(lr)
    # the 16 collinear horizon columns leave the spectrum well short of full rank
    assert effective_rank(singular_spectrum(An), 1e-3) <= An.shape[1] - 10


def test_an_uncertainty_blind_to_collinearity_fails_the_horizon_bound():
    """A test of the test (tests/broken.py): the per-texel uncertainty 1 / sqrt(G_jj + lr), each texel alone as if
    the others were known (what ignoring the columns' correlation gives), is the same for every unit-norm column
    and misses the bound above (horizon over the rest: 1.0, against the test's 3)."""
    grid, texel_index, A = sphere_shadow_transport()
    An = A / np.linalg.norm(A, axis=0)
    horizon = texel_index // grid.width == grid.height // 2 - 1
    lr = absolute_ridge(An, 1e-4)
    u = 1.0 / np.sqrt(np.einsum("ij,ij->j", An, An) + lr)
    assert not u[horizon].min() > 3 * u[~horizon].max(), u[horizon].min() / u[~horizon].max()


# --- plots ------------------------------------------------------------------------------------------------------

def test_plots_write_pngs(tmp_path):
    grid, texel_index, A = sphere_shadow_transport(height=4, side=12)
    lr = absolute_ridge(A, 1e-4)
    L = ridge_cholesky(A, lr)
    u = to_grid(texel_uncertainty(A, lr, L=L), grid, texel_index)
    h = scatter_to_image(leverage(A, lr, L=L), np.arange(A.shape[0]), (12, 12))
    gains = scatter_to_image(gain_images(A, lr, [0, 3]), np.arange(A.shape[0]), (12, 12))
    sv = singular_spectrum(A)
    paths = [
        plot_spectrum(sv, tmp_path / "spectrum.png", lr=lr),
        plot_envmap_map(u, tmp_path / "unc.png", title="texel uncertainty", units="radiance / pixel noise", log=True),
        plot_image_map(h, tmp_path / "lev.png", title="leverage h_ii", units="1", log=True),
        plot_image_map(gains[0], tmp_path / "gain.png", title="gain", units="radiance / pixel value", signed=True),
        plot_image_grid(gains, tmp_path / "gains.png", titles=["t0", "t3"], suptitle="gain images"),
    ]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == sorted(p.name for p in paths)  # no temp files left


# --- timing -----------------------------------------------------------------------------------------------------

def test_timing_16k_pixels_1k_texels():
    rng = np.random.default_rng(0)
    A = rng.random((16384, 1024), dtype=np.float32)
    A *= rng.random((16384, 1024), dtype=np.float32) < 0.3
    t0 = time.perf_counter()
    lr = absolute_ridge(A, 1e-4)
    L = ridge_cholesky(A, lr)
    h = leverage(A, lr, L=L)
    u = texel_uncertainty(A, lr, L=L)
    dt = time.perf_counter() - t0
    assert h.shape == (16384,) and u.shape == (1024,)
    assert np.all(np.isfinite(h)) and np.all(np.isfinite(u))
    assert dt < 15.0, f"leverage + uncertainty took {dt:.1f} s"
