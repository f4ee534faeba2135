"""Compact sources at the sub-texel position the photo gives them (``transport.texel_kernel``'s ``point`` candidate).

A source smaller than a texel (a lamp, the sun) lies somewhere inside one. A box column spreads its shadows over
the texel's 5.6 deg (at 32 x 64) and the narrow kernel sharpens them about the texel's centre; neither puts them
where the source is, so a lamp between two texel centres comes back split over two texels, a third of its energy
a row away (the hard suite's band misses, bench/results.md, issue 22) with dark rings where the columns' shadows
disagree with the photo's. Here the photo places the source:

1. for each bright blob of the box solve (objcam.solvers.sources.bright_blobs: above 10 x the median, any size;
   the MAX_BLOBS with the most light), brightest first, the residual with the light of the blob and the texels
   about it (where the box solve drew the rings that sharpen its shadows) above the sky around them (the median
   of the next ring) put back: what a source there has to explain;
2. the point whose light best explains it (per channel, a non-negative amplitude by least squares; the score is
   the drop in the sum of squares), first at the centres of the blob's brightest texels and their neighbours,
   then on three finer lattices about the best (1/4 of a texel with a few sub-pixel samples, 1/16 and 1/64 with
   all of them: the score's optimum is flat to parts in 1e4 there). A point's light is the column step 3 gives
   it: its direct light plus the indirect part of the box column of the texel holding it. The residual holds the
   source's bounce light too, and a point fitted with its direct light alone moves to where that mimics the
   bounce (a lamp near the zenith over a chair seen from 60 deg: placed 2.3 deg off, towards lighting the back's
   front faces, which the seat lights; bench/results.md, issue 22, session 46);
3. the texel holding the point gets the point's direct light (all sub-pixel samples) times the texel's solid
   angle as its column, so the texel's value stays its mean radiance; its indirect part is kept (it varies slowly
   with the direction). The solve then holds the source in the texel that contains it.

Each target gets its own A with its own sources (another target's lamp is not in its sky), and keeps it only
where its fit beats box texels' and the other kernels' (objcam.transport.kernel.pick: the verdict's chi2 per
fitted value).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from objcam.dr_memory import padded
from objcam.envmap import EnvGrid
from objcam.metrics import LUMA
from objcam.scene import use_mitsuba
from objcam.solvers.sources import rim_of

#: the search: the centres of the blob's core texels and their neighbours, then 5 x 5 lattices about the best at
#: 1/4, 1/16 and 1/64 of a texel, each covering the previous step (a lamp placed to ~0.05 deg at 32 rows; 3 x 3
#: at 1/64 was measured: 3 suite targets 0.004-0.029 worse, no faster)
REFINE_STEPS = (1.0 / 4.0, 1.0 / 16.0, 1.0 / 64.0)
#: the brightest blobs searched (the suite's rooms have 5 lamps; as objcam.solvers.sources)
MAX_BLOBS = 6
#: sub-pixel samples per pixel in the search, as a fraction of the part's own (support 32 -> 4, object 256 -> 32)
SEARCH_FRACTION = 8
#: a blob's core: its texels at or above this fraction of its peak luminance (the lattice covers them, grown by
#: one texel)
CORE_LEVEL = 0.5


@dataclass
class PointSource:
    """One source found: its unit direction (3,), the grid texel (flat index) holding it, the per-channel
    amplitudes (3,) in the texel's radiance units and the drop in the residual's sum of squares it gave."""

    direction: np.ndarray
    texel: int
    amplitude: np.ndarray
    gain: float

    def record(self) -> dict:
        el = float(np.degrees(np.arcsin(np.clip(self.direction[2], -1.0, 1.0))))
        az = float(np.degrees(np.arctan2(self.direction[1], self.direction[0])) % 360.0)
        return {"elevation_deg": round(el, 3), "azimuth_deg": round(az, 3), "texel": int(self.texel),
                "radiance": [round(float(a), 6) for a in self.amplitude], "gain": float(self.gain)}


def grid_directions(grid: EnvGrid, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(D, 3) unit directions at continuous grid coordinates: ``u`` (D,) rows (0 at the zenith, ``grid.height`` at
    the nadir), ``v`` (D,) columns (azimuth 2 pi v / W)."""
    theta = np.pi * np.clip(u, 0.0, grid.height) / grid.height
    phi = 2.0 * np.pi * np.asarray(v) / grid.width
    return np.stack([np.cos(phi) * np.sin(theta), np.sin(phi) * np.sin(theta), np.cos(theta)], axis=-1)


def point_direct(dm, dirs: np.ndarray, samples: int | None = None) -> np.ndarray:
    """(C, M, D) float32 direct light of point sources of unit energy (radiance x solid angle) in the directions
    ``dirs`` (D, 3), for the pixels of the DirectModel ``dm``: rho / pi x the mean over the pixel's first
    ``samples`` sub-pixel samples (a stratified prefix; default all) of V max(0, n . w).

    Shadow rays only where the direction lies inside the pixel's cone towards the occluders or crosses a sample's
    horizon (DirectModel's conservative cones, ``occ_cos`` and ``n_sin``; every pixel for directions at or below
    the horizon): elsewhere V = 1 and the value is q . w over all the pixel's samples, exact. One lane per traced
    (pixel, direction) pair, looping over the samples (as DirectModel._trace). (A disc of the source's angular
    size instead, its radius fitted to the penumbrae, was measured and dropped: the residual's fit moved by parts
    in 1e5 across 0-3 deg and the solve's chi2 favoured the point; bench/results.md, issue 22, session 30.)"""
    import drjit as dr

    mi = use_mitsuba()
    s = dm.s
    n_sub = dm.n_sub
    k = n_sub if samples is None else max(1, min(int(samples), n_sub))
    dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
    n_dir, nc = dirs.shape[0], dm.c
    # above every sample's horizon and outside the occluders' cone: q . w, exact (DirectModel's analytic part)
    out = np.einsum("cmx,dx->cmd", dm.q32, dirs.astype(np.float32))
    trace = ((dm.axis @ dirs.T >= dm.occ_cos[:, None]) | (dm.nbar @ dirs.T <= dm.n_sin[:, None])
             | (dirs[:, 2] <= 0)[None, :])
    pix, di = np.nonzero(trace)
    if pix.size == 0:
        return out
    d = dm._dr or dm._init_drjit()
    Col = mi.Float if nc == 1 else mi.Color3f
    scene = dm.geo.mi_scene
    wd = mi.Vector3f(*(padded(dirs[:, i], np.float32) for i in range(3)))
    dr.make_opaque(wd)
    per = max(1, dm.batch_rays // k)
    scale = float(1.0 / (np.pi * k))
    for a in range(0, pix.size, per):
        b = min(pix.size, a + per)
        pa = mi.UInt32(padded(pix[a:b], np.uint32))
        w = dr.gather(mi.Vector3f, wd, mi.UInt32(padded(di[a:b], np.uint32)))
        base = pa * n_sub

        def body(i, acc):
            ps = base + i
            o = dr.gather(mi.Point3f, d["P"], ps)
            n = dr.gather(mi.Vector3f, d["N"], ps)
            hit = dr.gather(mi.Bool, d["H"], ps)
            cosw = dr.dot(n, w)
            active = hit & (cosw > 0)
            occluded = scene.ray_test(mi.Ray3f(o, w), active)
            seen = dr.select(active & ~occluded, cosw, 0.0)
            return i + 1, acc + Col(seen) * dr.gather(Col, d["R"], ps)

        _, acc = dr.while_loop(state=(dr.zeros(mi.UInt32, b - a), dr.zeros(Col, b - a)),
                               cond=lambda i, *_: i < k, body=body, labels=("i", "acc"))
        dr.eval(acc)
        v = np.asarray(acc, dtype=np.float32)
        out[:, pix[a:b], di[a:b]] = (v.reshape(1, -1) if v.ndim == 1 else v) * scale  # Color3f: (3, lanes)
    return out


def split_point_direct(direct, dirs: np.ndarray, search: bool) -> np.ndarray:
    """(C, M, D) :func:`point_direct` over the parts of a SplitDirect (support and object pixels, each with its own
    sub-pixel samples); ``search``: a 1 / SEARCH_FRACTION prefix of each part's samples, else all of them."""
    out = None
    for rows, dm in direct.parts:
        k = max(1, dm.n_sub // SEARCH_FRACTION) if search else None
        cols = point_direct(dm, dirs, k)
        if out is None:
            out = np.zeros((cols.shape[0], direct.m, cols.shape[2]), np.float32)
        out[:, rows] = cols
    return out


def _predict(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(M, 3) float64 A x for A (C, M, N) float32 with C = 1 (grey: every channel through A[0]) or 3, x (N, 3);
    float32 products (A's own precision, as the solve's prediction)."""
    x = np.asarray(x, np.float32)
    if A.shape[0] == 1:
        return (A[0] @ x).astype(np.float64)
    return np.stack([A[c] @ x[:, c] for c in range(3)], axis=1).astype(np.float64)


def _fit(cols: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per direction, the non-negative per-channel amplitudes (D, 3) of the columns ``cols`` (C, M, D) against the
    residual r (M, 3) and the drop in the sum of squares (D,) they give."""
    cols = np.asarray(cols, np.float64)
    amp = np.zeros((cols.shape[2], 3))
    gain = np.zeros(cols.shape[2])
    for c in range(3):
        k = cols[0] if cols.shape[0] == 1 else cols[c]
        num = k.T @ r[:, c]
        den = np.einsum("md,md->d", k, k)
        amp[:, c] = np.where(den > 0, np.maximum(num, 0.0) / np.maximum(den, 1e-300), 0.0)
        gain += amp[:, c] * num
    return amp, gain


def _lattice(centre: tuple[float, float], step: float, grid: EnvGrid) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of the 5 x 5 positions ``step`` apart about ``centre`` (grid coordinates), u inside the grid."""
    off = step * np.arange(-2, 3)
    du, dv = np.meshgrid(off, off, indexing="ij")
    return np.clip(centre[0] + du.ravel(), 1e-6, grid.height - 1e-6), centre[1] + dv.ravel()


def background(direct, texels: np.ndarray) -> np.ndarray:
    """(1, M, B) float32: the light of the texels ``texels`` (B,) that pixels see directly past the scene (each
    DirectModel's ``bg``, 1 / S per sample that misses the scene towards the texel); zero where no pixel does."""
    out = np.zeros((1, direct.m, len(texels)), np.float32)
    for rows, dm in direct.parts:
        if dm.bg is not None:
            out[0, rows] = dm.bg[:, texels].toarray().astype(np.float32)
    return out


class TexelBounce:
    """What :func:`point_columns` keeps beside a point's direct light, per unit energy: for a direction, (A's
    column - the box direct light + the background seen past the scene) / the solid angle of the texel holding
    it, i.e. the box column's indirect part (it varies slowly with the direction) and the sky seen past the scene.
    Zero for a texel A does not hold; each texel's box light computed once."""

    def __init__(self, direct, grid: EnvGrid, texel_index: np.ndarray, A: np.ndarray):
        self.direct, self.grid, self.A = direct, grid, A
        self.where = {int(t): i for i, t in enumerate(texel_index)}
        self.omega = grid.solid_angles().ravel()
        self.cache: dict[int, np.ndarray] = {}

    def of_texel(self, j: int) -> np.ndarray:
        """(C, M) float32: texel ``j``'s indirect light and sky seen past the scene, per unit energy."""
        if j not in self.cache:
            if j not in self.where:
                self.cache[j] = np.zeros(self.A.shape[:2], np.float32)
            else:
                tex = np.array([j])
                kept = self.A[:, :, self.where[j]] - (self.direct.columns(tex) - background(self.direct, tex))[:, :, 0]
                self.cache[j] = kept / np.float32(self.omega[j])
        return self.cache[j]

    def at(self, dirs: np.ndarray) -> np.ndarray:
        """(C, M, D) float32 for the unit directions ``dirs`` (D, 3)."""
        row, col = self.grid.texel_of(np.asarray(dirs, np.float64).reshape(-1, 3))
        return np.stack([self.of_texel(int(j)) for j in np.asarray(row) * self.grid.width + np.asarray(col)],
                        axis=-1)


def find_sources(direct, grid: EnvGrid, texel_index: np.ndarray, A: np.ndarray, y: np.ndarray, use: np.ndarray,
                 x: np.ndarray, blobs: list[np.ndarray]) -> list[PointSource]:
    """The point source of each blob. direct: the box A's SplitDirect; A (C, M, N) the box A, y (M, 3) the target,
    use (M,) the fitted pixels, x (N, 3) the box solve; blobs: per blob the positions (into the N texels) of its
    texels, brightest blob first. Each blob's light is put back into the residual, its point fitted and taken
    out, before the next."""
    rows_n = texel_index // grid.width
    cols_n = texel_index % grid.width
    bounce = TexelBounce(direct, grid, texel_index, A)

    def light(dirs: np.ndarray, search: bool) -> np.ndarray:
        """(C, fitted pixels, D): the points' columns per unit energy, as point_columns will give them."""
        return (split_point_direct(direct, dirs, search) + bounce.at(dirs))[:, use]

    r = y[use] - _predict(A, x)[use]
    lum = x @ LUMA
    found = []
    held = np.zeros(x.shape[0], bool)
    if blobs:
        held[np.concatenate(blobs)] = True
    for blob in blobs:
        # what a point has to explain: the light of the blob and of the texels about it (where the box solve drew
        # the rings that sharpen its shadows) above the sky around them (the next ring's median)
        near = np.union1d(blob, rim_of(blob, grid, texel_index, held))
        rim = rim_of(near, grid, texel_index, held)
        sky = np.median(x[rim], axis=0) if rim.size else np.zeros(3)
        r_b = r + _predict(A[:, :, near][:, use], x[near] - sky[None, :])
        core = blob[lum[blob] >= CORE_LEVEL * lum[blob].max()]
        # coarse: the centres of the core texels and their neighbours
        cells = {(int(rows_n[p]) + dr_, (int(cols_n[p]) + dc) % grid.width)
                 for p in core for dr_ in (-1, 0, 1) for dc in (-1, 0, 1) if 0 <= rows_n[p] + dr_ < grid.height}
        cells = np.array(sorted(cells), float)
        u, v = cells[:, 0] + 0.5, cells[:, 1] + 0.5
        _, gain = _fit(light(grid_directions(grid, u, v), True), r_b)
        best = int(np.argmax(gain))
        centre = (float(u[best]), float(v[best]))
        for level, step in enumerate(REFINE_STEPS):
            u, v = _lattice(centre, step, grid)
            dirs = grid_directions(grid, u, v)
            cols = light(dirs, level == 0)  # the finer lattices with every sample
            amp, gain = _fit(cols, r_b)
            best = int(np.argmax(gain))
            centre = (float(u[best]), float(v[best]))
        if gain[best] <= 0:  # the last lattice's columns are the point's own (all samples)
            continue
        r = r_b - _predict(cols[:, :, best : best + 1], amp[best : best + 1])
        row, col = grid.texel_of(dirs[best])
        j = int(row * grid.width + col)
        omega = float(grid.solid_angles().ravel()[j])
        found.append(PointSource(dirs[best], j, amp[best] / omega, float(gain[best])))
    return found


def point_columns(direct, grid: EnvGrid, texel_index: np.ndarray, sources: list[PointSource]
                  ) -> tuple[np.ndarray, np.ndarray, list[PointSource]]:
    """(positions into the N texels (B,), the change to A's direct light there (C, M, B) float32, the sources
    used): each source's texel gets the source's point light (all sub-pixel samples, times the texel's solid
    angle) in place of its box direct light; where two sources share a texel the one with the larger gain stays."""
    best: dict[int, PointSource] = {}
    for s in sources:
        if s.texel not in best or s.gain > best[s.texel].gain:
            best[s.texel] = s
    where = {int(t): i for i, t in enumerate(texel_index)}
    used = [s for t, s in sorted(best.items()) if t in where]
    if not used:
        return np.zeros(0, np.int64), np.zeros((0, direct.m, 0), np.float32), []
    tex = np.array([s.texel for s in used], np.int64)
    pos = np.array([where[int(t)] for t in tex], np.int64)
    omega = grid.solid_angles().ravel()[tex].astype(np.float32)
    pts = split_point_direct(direct, np.stack([s.direction for s in used]), False) * omega[None, None, :]
    box = direct.columns(tex)  # the box direct light, with the background seen past the scene (kept)
    return pos, pts + background(direct, tex) - box, used
