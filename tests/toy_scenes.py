"""Small renderer-free scenes shared by the solver tests: ground-plane pixels under occluding spheres, or under
random occluder cones."""

from __future__ import annotations

import numpy as np

from objcam.envmap import EnvGrid

SPHERES = [((0.0, 0.0, 0.5), 0.4), ((0.6, -0.3, 0.25), 0.2), ((-0.5, 0.6, 0.8), 0.15)]


def sphere_shadow_transport(grid: EnvGrid, m_side: int, spheres=SPHERES) -> tuple[np.ndarray, np.ndarray]:
    """Kept texels (upper hemisphere, flat indices (N,)) and A (M, N) float32 for an m_side x m_side grid of
    ground points on [-1.5, 1.5]^2 (A = visibility x cos x solid angle / pi: albedo 1) under
    ``spheres`` ((centre, radius) pairs)."""
    dirs = grid.directions().reshape(-1, 3)
    omega = grid.solid_angles().ravel()
    keep = np.flatnonzero(dirs[:, 2] > 0)
    dk, ok = dirs[keep], omega[keep]
    u = np.linspace(-1.5, 1.5, m_side)
    px, py = np.meshgrid(u, u)
    P = np.stack([px.ravel(), py.ravel(), np.zeros(px.size)], 1)
    vis = np.ones((P.shape[0], dk.shape[0]), bool)
    for c, r in spheres:
        oc = np.asarray(c)[None, :] - P
        tca = oc @ dk.T
        d2 = (oc**2).sum(1)[:, None] - tca**2
        vis &= ~((tca > 0) & (d2 < r * r))
    A = (vis * (dk[:, 2] * ok)[None, :] / np.pi).astype(np.float32)
    return keep, A


def toy_transport(A: np.ndarray, grid: EnvGrid, keep: np.ndarray, side: int):
    """An objcam.transport.Transport of a grey A (M, N) on the texels ``keep`` (N,) of ``grid``: direct light,
    albedo 1, every one of the side x side (= M) pooled pixels kept."""
    from objcam.transport.storage import Transport

    m = A.shape[0]
    return Transport(A=A[None].astype(np.float32), pixel_index=np.arange(m), image_shape=(side, side), downsample=1,
                     texel_index=keep, env_height=grid.height, directions=grid.directions().reshape(-1, 3)[keep],
                     solid_angle=grid.solid_angles().ravel()[keep], albedo=np.ones((m, 3), np.float32),
                     unknown_albedo=np.zeros(m, bool), coverage=np.ones(m, np.float32),
                     object_fraction=np.zeros(m, np.float32), model="direct", samples=None, spp=None, max_depth=2,
                     camera=None)


def sphere_shadow_toy(grid: EnvGrid, side: int):
    """A :func:`toy_transport` of :func:`sphere_shadow_transport` (side x side ground points) and its kept texels
    (N,)."""
    keep, A = sphere_shadow_transport(grid, side)
    return toy_transport(A, grid, keep, side), keep


def sky_with_sun(grid: EnvGrid, keep: np.ndarray, sun: float) -> np.ndarray:
    """(H, W, 3) sky gradient plus a one-texel sun of ``sun`` x the mean sky radiance over the kept texels."""
    theta, phi = grid.centres()
    sky = (0.5 + 0.5 * np.cos(theta)) * (1 + 0.3 * np.cos(phi))
    truth = np.stack([sky, 0.9 * sky, 1.2 * sky], -1)
    mean = truth.reshape(-1, 3)[keep].mean()
    truth[grid.height // 4, grid.width // 3] += sun * mean * np.array([1.0, 0.95, 0.8])
    return truth


def cone_shadow_transport(grid: EnvGrid, texels: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """(m, len(texels)) A of m plane pixels, each under a random occluder cone: shadow-like 0/1 visibility times
    cosine times solid angle / pi. Draws the cones' axes and widths from ``rng`` (in that order)."""
    dirs = grid.directions().reshape(-1, 3)[texels]
    axes = rng.normal(size=(m, 3))
    axes[:, 2] = np.abs(axes[:, 2]) + 0.3
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    vis = (axes @ dirs.T) < rng.uniform(0.6, 0.95, size=(m, 1))
    return vis * np.maximum(dirs[:, 2], 0)[None] * grid.solid_angles().ravel()[texels][None] / np.pi


#: the sun-and-sky toy of :func:`sun_sky_toy`: per-pixel noise relative to the median pixel, and the known-albedo
#: edge prior's smoothness rule at that noise (objcam.solvers.plan.defaults.EDGE_LS_PER_SIGMA)
TOY_NOISE = 0.01
TOY_LS = 1.5 * TOY_NOISE


def sun_sky_toy(height: int = 16, side: int = 40, sun: float = 30.0):
    """(transport, grid, truth (H, 2H, 3), clean photo (side^2, 3)): :func:`sphere_shadow_toy` under
    :func:`sky_with_sun`, the photo without noise."""
    grid = EnvGrid(height)
    tr, keep = sphere_shadow_toy(grid, side)
    truth = sky_with_sun(grid, keep, sun=sun)
    return tr, grid, truth, tr.predict(tr.x_from_envmap(truth)).reshape(-1, 3)


def solve_toy(tr, grid, y: np.ndarray, sigma_abs: float, **params):
    """The known-albedo edge solve (objcam.solvers.plan.known.solve_known_edges) of photo y (M, 3) on every pixel at
    TOY_LS, with SolveParams(**params); asserts it is exact. Returns (X, info, rejected)."""
    from objcam.solvers.plan.known import solve_known_edges
    from objcam.solvers.plan.params import SolveParams

    use = np.ones(len(y), bool)
    X, kkt, _, _, info, rejected = solve_known_edges(tr, grid, use, y, TOY_LS, 1e-4, SolveParams(**params), None,
                                                     sigma_abs)
    assert kkt.max() < 1e-6
    return X, info, rejected


def lobe_scene(seed: int, visibility: float | None, height: int = 16):
    """(grid, texel_index (N,), A (1, M, N) float32, rng): the upper half of a ``height`` x 2 ``height`` grid seen
    by M = 800 clamped cosine lobes of random normals (a Lambertian kernel, smooth in direction: a lamp's place is
    barely seen, and blind to a sky's odd azimuthal harmonics of order >= 3), times a random 0/1 visibility per
    (pixel, texel) when ``visibility`` is given (shadows: every direction's column its own). ``rng`` continues
    the draws, for the photo's noise."""
    rng = np.random.default_rng(seed)
    grid = EnvGrid(height)
    texel_index = np.arange(grid.n_texels // 2)  # the rows above the horizon
    d = grid.directions().reshape(-1, 3)[texel_index]
    n = rng.normal(size=(800, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.5
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    A = np.maximum(n @ d.T, 0.0) * grid.solid_angles().reshape(-1)[texel_index][None, :]
    if visibility is not None:
        A = A * (rng.random(A.shape) < visibility)
    return grid, texel_index, A[None].astype(np.float32), rng
