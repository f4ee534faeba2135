"""Path-traced images of a Mitsuba scene through an objcam :class:`~objcam.camera.Camera`.

objcam generates the camera rays itself (``Camera.rays``' model: OpenCV pinhole, pixel (u, v) centred at integer
coordinates, a box pixel filter over [u - 1/2, u + 1/2] x [v - 1/2, v + 1/2], fx and fy independent) and hands
them to Mitsuba's ``path`` integrator; no Mitsuba sensor or film is involved, so Mitsuba's own pixel conventions
(pixel centres at +0.5, a single focal length) never enter. Every camera and scene quantity reaches the kernel
as an opaque value, so repeated renders of the same size and depth reuse the compiled kernel.

:func:`mitsuba_box_bitmap` turns an envmap of box texels (objcam's convention) into a bitmap whose bilinear
lookup in Mitsuba reproduces the box texels up to thin ramps at texel boundaries.
"""

from __future__ import annotations

import numpy as np

from objcam.camera import Camera
from objcam.dr_memory import padded

# Lanes (camera samples) per kernel launch: bounds the memory of one wavefront (~0.3 GB at 2**20 lanes).
MAX_LANES = 1 << 20

_INTEGRATORS: dict[tuple[str, int], object] = {}


def _integrator(mi, max_depth: int):
    key = (mi.variant(), int(max_depth))
    if key not in _INTEGRATORS:
        _INTEGRATORS[key] = mi.load_dict({"type": "path", "max_depth": int(max_depth), "hide_emitters": False})
    return _INTEGRATORS[key]


def _pass_seed(seed: int, index: int) -> int:
    """A 32-bit seed per (seed, pass) with no collisions between nearby pairs."""
    x = (int(seed) * 0x9E3779B1 + int(index) * 0x85EBCA77 + 0x27D4EB2F) & 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    return x


def _trace(mi, dr, scene, n: int, spp: int, max_depth: int, seed: int, make_ray) -> np.ndarray:
    """Mean radiance (n, 3) over ``spp`` samples per ray; ``make_ray(index, sampler)`` builds the rays of one
    launch from the UInt32 ray index of every lane (it must draw exactly one 2D sample)."""
    spp = int(spp)
    if spp < 1:
        raise ValueError("spp must be >= 1")
    integrator = _integrator(mi, max_depth)
    spp_pass = max(1, min(spp, MAX_LANES // n))  # every ray gets spp_pass samples per launch
    n_passes = -(-spp // spp_pass)
    acc = np.zeros((n, 3), dtype=np.float64)
    done = 0
    sampler = mi.load_dict({"type": "independent"})
    for p in range(n_passes):
        k = min(spp_pass, spp - done)
        lanes = n * k
        sampler.seed(dr.opaque(mi.UInt32, _pass_seed(seed, p)), lanes)
        index = dr.arange(mi.UInt32, lanes) // dr.opaque(mi.UInt32, k)
        ray = make_ray(index, sampler)
        spec, _, _ = integrator.sample(scene, sampler, mi.RayDifferential3f(ray), None, True)
        spec = dr.select(dr.isfinite(spec), spec, 0.0)  # drop the rare NaN/inf sample, as Mitsuba's film does
        summed = dr.block_sum(mi.Color3f(spec), k) if k > 1 else mi.Color3f(spec)
        acc += np.asarray(summed, dtype=np.float64).reshape(3, n).T
        done += k
    return (acc / spp).astype(np.float32)


def trace_rays(scene, origins: np.ndarray, directions: np.ndarray, spp: int, max_depth: int,
               seed: int = 0) -> np.ndarray:
    """Mean path-traced radiance (N, 3) arriving along N world rays (``origins`` and unit ``directions`` (N, 3),
    metres), ``spp`` samples each, no jitter. ``max_depth`` as Mitsuba's ``path`` integrator."""
    from objcam.scene import use_mitsuba

    mi = use_mitsuba()
    import drjit as dr

    o = np.ascontiguousarray(np.reshape(origins, (-1, 3)), dtype=np.float32)
    d = np.asarray(np.reshape(directions, (-1, 3)), dtype=np.float64)
    d = np.ascontiguousarray(d / np.linalg.norm(d, axis=1, keepdims=True), dtype=np.float32)
    n = len(o)
    if n == 0:
        return np.zeros((0, 3), dtype=np.float32)
    oo = mi.Point3f(*(mi.Float(padded(o[:, i])) for i in range(3)))  # objcam.dr_memory
    dd = mi.Vector3f(*(mi.Float(padded(d[:, i])) for i in range(3)))

    def make_ray(index, sampler):
        sampler.next_2d()  # the same sample dimensions as render_rays
        return mi.Ray3f(dr.gather(mi.Point3f, oo, index), dr.gather(mi.Vector3f, dd, index))

    return _trace(mi, dr, scene, n, spp, max_depth, seed, make_ray)


def render_rays(scene, u: np.ndarray, v: np.ndarray, camera: Camera, spp: int, max_depth: int, seed: int = 0,
                jitter: bool = True) -> np.ndarray:
    """Mean path-traced radiance (N, 3) for N continuous pixel positions ``u, v`` of ``camera``.

    With ``jitter`` each sample position is drawn uniformly from [u - 1/2, u + 1/2] x [v - 1/2, v + 1/2] (a box
    pixel filter), otherwise every sample goes through (u, v) exactly. ``max_depth`` follows Mitsuba's ``path``
    integrator (1: emitters seen directly, 2: direct illumination only, -1: unbounded).
    """
    from objcam.scene import use_mitsuba

    mi = use_mitsuba()
    import drjit as dr

    u = np.ascontiguousarray(np.ravel(u), dtype=np.float32)
    v = np.ascontiguousarray(np.ravel(v), dtype=np.float32)
    n = u.size
    if n == 0:
        return np.zeros((0, 3), dtype=np.float32)
    m = camera.matrix
    rot = [dr.opaque(mi.Float, float(m[i, j])) for i in range(3) for j in range(3)]
    ctr = mi.Point3f(*(dr.opaque(mi.Float, float(m[i, 3])) for i in range(3)))
    fx, fy = dr.opaque(mi.Float, camera.fx), dr.opaque(mi.Float, camera.fy)
    cx, cy = dr.opaque(mi.Float, camera.cx), dr.opaque(mi.Float, camera.cy)
    uu, vv = mi.Float(padded(u)), mi.Float(padded(v))

    def make_ray(index, sampler):
        pu, pv = dr.gather(mi.Float, uu, index), dr.gather(mi.Float, vv, index)
        j = sampler.next_2d()
        if jitter:
            pu, pv = pu + j.x - 0.5, pv + j.y - 0.5
        xc, yc = (pu - cx) / fx, (pv - cy) / fy
        d = mi.Vector3f(rot[0] * xc + rot[1] * yc + rot[2],
                        rot[3] * xc + rot[4] * yc + rot[5],
                        rot[6] * xc + rot[7] * yc + rot[8])
        return mi.Ray3f(ctr, dr.normalize(d))

    return _trace(mi, dr, scene, n, spp, max_depth, seed, make_ray)


def render_image(scene, camera: Camera, spp: int, max_depth: int, seed: int = 0) -> np.ndarray:
    """Linear radiance (H, W, 3) float32 of ``scene`` seen by ``camera``: pixel (u, v) (column, row) is the mean
    radiance over [u - 1/2, u + 1/2] x [v - 1/2, v + 1/2] (box filter, OpenCV pixel centres at integers).

    scene: a Mitsuba scene (e.g. from :func:`objcam.scene.build_mitsuba_scene`; any sensor in it is ignored).
    spp: samples per pixel. max_depth: as Mitsuba's ``path`` integrator (2 = direct light only).
    seed: different seeds give independent noise; the same seed, the same image.
    """
    vv, uu = np.meshgrid(np.arange(camera.height, dtype=np.float32), np.arange(camera.width, dtype=np.float32),
                         indexing="ij")
    out = render_rays(scene, uu, vv, camera, spp, max_depth, seed)
    return out.reshape(camera.height, camera.width, 3)


def _ramp_weights(theta_b: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """Solid-angle weights (per unit azimuth) of the bilinear hat of a row at polar angle ``theta_b`` over
    [theta_b - delta, theta_b] (upper) and [theta_b, theta_b + delta] (lower)."""

    def prim(t, a):  # antiderivative of (t - a) sin t
        return np.sin(t) - t * np.cos(t) + a * np.cos(t)

    a = theta_b - delta
    upper = (prim(theta_b, a) - prim(a, a)) / delta
    b = theta_b + delta
    lower = -(prim(b, b) - prim(theta_b, b)) / delta
    return upper, lower


def mitsuba_box_bitmap(env: np.ndarray, upsample: int = 4) -> np.ndarray:
    """An array that, passed as ``envmap`` to :func:`objcam.scene.build_mitsuba_scene`, makes Mitsuba emit the box
    texels of ``env`` (H, 2H[, C], objcam's convention) up to thin ramps at texel boundaries.

    Mitsuba's envmap interpolates bilinearly between samples that sit at theta = pi * i / (H' - 1) (rows) and at
    the column centres (with wrap-around), so a plain low-resolution bitmap is blurred over whole texels and its
    rows are shifted. The result here has H' = upsample * H + 1 rows and W' = upsample * W columns (objcam's column
    order; build_mitsuba_scene reverses them for Mitsuba): row i samples theta = pi * i / (upsample * H), so every
    texel boundary falls on a row; columns are repeated ``upsample`` times. The bilinear blur is then a linear ramp
    of half-width 1 / upsample texel about each texel boundary. In azimuth it is symmetric, so every texel's
    emitted power is exact; in polar angle the boundary row holds the mean of its two texels weighted by the solid
    angle under each half of its ramp, which makes every texel's emitted power exact too (the ramp only moves a
    sliver of it, about 1 / (4 upsample) of a texel row, across the boundary). The zenith and nadir rows are the
    first and last texel rows. tests/test_conventions.py measures the result through Mitsuba.
    """
    env = np.asarray(env, dtype=np.float32)
    squeeze = env.ndim == 2
    e = env[..., None] if squeeze else env
    f = int(upsample)
    if f < 1:
        raise ValueError("upsample must be >= 1")
    h = e.shape[0]
    cols = np.repeat(e, f, axis=1).astype(np.float64)  # (H, W f, C)
    rows = np.repeat(cols, f, axis=0)  # row r f + k holds texel row r
    rows = np.concatenate([rows, cols[h - 1 :]], axis=0)  # the nadir row
    if h > 1:
        theta_b = np.pi * np.arange(1, h) / h  # boundaries between texel rows r - 1 and r, at bitmap row r f
        wu, wl = _ramp_weights(theta_b, np.pi / (h * f))
        wu, wl = (wu / (wu + wl))[:, None, None], (wl / (wu + wl))[:, None, None]
        rows[f * np.arange(1, h)] = wu * cols[:-1] + wl * cols[1:]
    rows = rows.astype(np.float32)
    return rows[..., 0] if squeeze else rows
