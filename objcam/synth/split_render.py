"""Low-variance global-illumination renders: direct light by stratified quadrature, indirect by path tracing.

A plain path-traced image at 2048 spp still carries 1-2% Monte Carlo noise per pixel on a shadowed scene, almost
all of it from the direct term (which envmap texel the one emitter sample picks, and whether it is occluded).
Benchmarks that want a target at ~0.1% noise split the estimator, which stays unbiased:

- direct = sum over the cells of a (theta, phi) grid on the upper hemisphere of one jittered shadow ray each
  (area-uniform inside the cell, weight = the cell's solid angle), per pixel, each ray with its own jittered
  sub-pixel position (box filter); bright cells are split further. With ~20k cells per pixel the direct term is
  integrated by stratified sampling; the radiance is Mitsuba's own emitter lookup, so it is exactly the function
  the path tracer sees.
- indirect = path(max_depth) - path(2) rendered with the same seed: the two runs draw identical random numbers
  for the first vertex (Mitsuba's ``path`` integrator consumes them in the same order), so the direct samples
  cancel exactly and what remains is the light of two and more bounces, with the noise of that part only.

Neither part uses objcam's transport code, so the target stays independent of the model it tests.
"""

from __future__ import annotations

import numpy as np

from objcam.camera import Camera
from objcam.dr_memory import padded
from objcam.render import _pass_seed, render_image

# Lanes per kernel launch (~0.3 GB of wavefront state at 2**22 lanes in the llvm variant).
_LANES = 1 << 22


def direction_strata(envmap: np.ndarray, rows: int, budget: float = 1.0, max_split: int = 32,
                     horizon_rows: int = 2) -> np.ndarray:
    """Cells of a (theta, phi) grid with energy-adaptive subdivision: (S, 4) float64 rows of
    (cos theta top, cos theta bottom, phi start, phi width), radians.

    The grid has ``rows`` x 2 ``rows`` cells on the upper hemisphere plus ``horizon_rows`` rows below it (light
    from below the support plane's horizon is blocked by the plane, up to a sliver that escapes past its edge).
    A cell of energy share e (radiance x solid angle of ``envmap`` (H, 2H, 3) over the cell) is split into
    g x g sub-cells, g = ceil(sqrt(e x budget x n_cells)) clipped to ``max_split``: a bright texel's radiance
    ramps to its neighbours inside the cell in Mitsuba's lookup, and one ray there would dominate the noise.
    """
    rows = int(rows)
    cols = 2 * rows
    lum = np.asarray(envmap, dtype=np.float64)[..., :3].mean(axis=-1)
    h = lum.shape[0]
    # energy per cell: box-average the envmap onto the cell grid (cells and texels share edges when h % rows == 0)
    theta_t = (np.arange(h) + 0.5) * np.pi / h
    energy_t = lum * np.sin(theta_t)[:, None]
    ri = np.minimum((np.arange(h) * rows) // h, rows - 1)
    ci = np.minimum((np.arange(2 * h) * cols) // (2 * h), cols - 1)
    energy = np.zeros((rows, cols))
    np.add.at(energy, (ri[:, None], ci[None, :]), energy_t)
    n_rows = min(rows, rows // 2 + int(horizon_rows))
    energy = energy[:n_rows]
    share = energy / max(energy.sum(), 1e-300)
    g = np.clip(np.ceil(np.sqrt(share * budget * share.size)), 1, max_split).astype(int)
    out = []
    for r in range(n_rows):
        for c in range(cols):
            k = g[r, c]
            t = (r + np.arange(k + 1) / k) * np.pi / rows
            z = np.cos(t)
            p0 = (c + np.arange(k) / k) * 2 * np.pi / cols
            for a in range(k):
                for b in range(k):
                    out.append((z[a], z[a + 1], p0[b], 2 * np.pi / cols / k))
    return np.asarray(out, dtype=np.float64)


def render_direct_strata(scene, camera: Camera, strata: np.ndarray, seed: int = 0, progress=None) -> np.ndarray:
    """Direct light (H, W, 3) float32 radiance of ``scene`` seen by ``camera`` (box pixel filter).

    strata: (S, 4) cells from :func:`direction_strata`; per pixel one shadow ray in each cell, area-uniform inside
    it, with its own jittered sub-pixel position. Directions outside the cells contribute nothing.
    The world frame is objcam's (z up); the scene's envmap emitter must be its only light.
    """
    from objcam.scene import use_mitsuba

    mi = use_mitsuba()
    import drjit as dr

    cells = np.asarray(strata, dtype=np.float32)
    n_cells = len(cells)
    cz0, cz1, cp0, cdp = (mi.Float(padded(cells[:, i])) for i in range(4))  # objcam.dr_memory
    n_pix = camera.width * camera.height
    chunk = max(1, min(n_cells, _LANES // n_pix))  # cells per launch; every pixel gets `chunk` lanes
    m = camera.matrix
    rot = [dr.opaque(mi.Float, float(m[i, j])) for i in range(3) for j in range(3)]
    ctr = mi.Point3f(*(dr.opaque(mi.Float, float(m[i, 3])) for i in range(3)))
    fx, fy = dr.opaque(mi.Float, camera.fx), dr.opaque(mi.Float, camera.fy)
    cx, cy = dr.opaque(mi.Float, camera.cx), dr.opaque(mi.Float, camera.cy)
    width = dr.opaque(mi.UInt32, camera.width)
    emitter = scene.environment()
    if emitter is None:
        raise ValueError("render_direct_strata needs a scene with an envmap emitter")
    ctx = mi.BSDFContext()
    acc = np.zeros((n_pix, 3), dtype=np.float64)
    sky_acc = np.zeros((n_pix, 3), dtype=np.float64)
    sampler = mi.load_dict({"type": "independent"})
    n_launch = -(-n_cells // chunk)
    for launch in range(n_launch):
        first = launch * chunk
        k = min(chunk, n_cells - first)
        lanes = n_pix * k
        sampler.seed(dr.opaque(mi.UInt32, _pass_seed(seed, launch)), lanes)
        lane = dr.arange(mi.UInt32, lanes)
        pix = lane // dr.opaque(mi.UInt32, k)
        cell = lane % dr.opaque(mi.UInt32, k) + dr.opaque(mi.UInt32, first)
        # camera ray through a jittered point of the pixel
        j = sampler.next_2d()
        pu = mi.Float(pix % width) + j.x - 0.5
        pv = mi.Float(pix // width) + j.y - 0.5
        xc, yc = (pu - cx) / fx, (pv - cy) / fy
        d = dr.normalize(mi.Vector3f(rot[0] * xc + rot[1] * yc + rot[2],
                                     rot[3] * xc + rot[4] * yc + rot[5],
                                     rot[6] * xc + rot[7] * yc + rot[8]))
        ray = mi.Ray3f(ctr, d)
        si = scene.ray_intersect(ray)
        hit = si.is_valid()
        # pixels that see the sky: the emitter's radiance along the camera ray (averaged over all lanes)
        si_sky = dr.zeros(mi.SurfaceInteraction3f)
        si_sky.wi = -d
        sky = dr.select(hit, mi.Color3f(0.0), mi.Color3f(emitter.eval(si_sky)))
        # one direction, area-uniform inside this lane's cell
        z0, z1 = dr.gather(mi.Float, cz0, cell), dr.gather(mi.Float, cz1, cell)
        p0, dp = dr.gather(mi.Float, cp0, cell), dr.gather(mi.Float, cdp, cell)
        s = sampler.next_2d()
        z = z0 + (z1 - z0) * s.x
        phi = p0 + dp * s.y
        sin_t = dr.safe_sqrt(1.0 - z * z)
        wd = mi.Vector3f(dr.cos(phi) * sin_t, dr.sin(phi) * sin_t, z)
        solid_angle = (z0 - z1) * dp
        bsdf = si.bsdf(ray)
        wo = si.to_local(wd)
        active = hit & (wo.z > 0)
        f = mi.Color3f(bsdf.eval(ctx, si, wo, active))  # albedo / pi * cos
        si_env = dr.zeros(mi.SurfaceInteraction3f)
        si_env.wi = -wd
        radiance = mi.Color3f(emitter.eval(si_env, active))
        visible = active & ~scene.ray_test(si.spawn_ray(wd), active)
        val = dr.select(visible, f * radiance * solid_angle, mi.Color3f(0.0))
        val = dr.select(dr.isfinite(val), val, mi.Color3f(0.0))
        acc += np.asarray(dr.block_sum(val, k) if k > 1 else val, dtype=np.float64).reshape(3, n_pix).T
        sky_acc += np.asarray(dr.block_sum(sky, k) if k > 1 else sky, dtype=np.float64).reshape(3, n_pix).T
        if progress is not None:
            progress.update(1)
    acc += sky_acc / n_cells
    return acc.reshape(camera.height, camera.width, 3).astype(np.float32)


def render_indirect(scene, camera: Camera, spp: int, max_depth: int, seed: int = 0) -> np.ndarray:
    """Light of two and more bounces (H, W, 3): path(max_depth) minus path(2) with the same random numbers."""
    full = render_image(scene, camera, spp, max_depth, seed=seed).astype(np.float64)
    direct = render_image(scene, camera, spp, 2, seed=seed).astype(np.float64)
    return (full - direct).astype(np.float32)


def render_split(scene, camera: Camera, spp_indirect: int, max_depth: int, strata: np.ndarray,
                 seed: int = 0) -> np.ndarray:
    """Global illumination (H, W, 3) float32 = :func:`render_direct_strata` over ``strata`` (from
    :func:`direction_strata`) + :func:`render_indirect` at ``spp_indirect``."""
    direct = render_direct_strata(scene, camera, strata, seed=seed)
    if max_depth == 2:
        return direct
    return (direct + render_indirect(scene, camera, spp_indirect, max_depth, seed=seed + 7919)).astype(np.float32)
