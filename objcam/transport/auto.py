"""``model=auto``: is direct light enough? Measure the indirect light on a sample of columns and, when leaving
it out would change the answer beyond what the target's noise explains, add an indirect correction to every column.

The decision is by the indirect light's effect on the fit, not by per-pixel magnitudes: the indirect image I is a
bias correlated over every pixel, while the noise is independent per pixel and averages out in the solve. Leaving
I out of A moves the solve by ``||I||^2 / sigma^2`` in whitened units (chi-squared), split between the residual
(the part of I no envmap explains) and the envmap (the part it absorbs: a shift of the recovered light measured
against the solve's own uncertainty). It is compared with the chi-squared's own spread over M pixel values,
``sqrt(2 M)``: the indirect light is modelled when its effect exceeds ``AUTO_EFFECT_Z`` times that spread
(:func:`indirect_effect`), or when pixels of known albedo pin an unknown albedo's scale and the indirect light
biases that scale by more than ``AUTO_EFFECT_Z`` times its noise (:func:`pinned_scale_effect`).

Indirect light of a column is measured as render(max_depth=D) - render(max_depth=2) with the same seed: both
renders draw the same random numbers for the camera ray and the first vertex, so their difference holds only
paths with two or more bounces, without the direct light's noise. It is smooth in the image (and in the light
direction), so it is rendered at a coarse pixel resolution (``scale``) and for blocks of g x g texels, then
interpolated to the kept pixels and shared among a block's texels in proportion to their solid angle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from objcam.envmap import EnvGrid
from objcam.progress import bar
from objcam.transport.path import PathRenderer


def laplacian_channels(image: np.ndarray, valid: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """Per channel of a linear image (H, W, C), over its valid pixels (H, W) bool whose whole 3 x 3 neighbourhood
    is valid: (the values (K,), |Laplacian| (K,) with Immerkaer's kernel, whose response to Gaussian noise of sigma
    has sigma 6 sigma and to smooth light none); None when fewer than 64 such pixels."""
    from scipy.ndimage import binary_erosion, convolve

    img = np.nan_to_num(np.asarray(image, dtype=np.float64))
    ok = binary_erosion(np.asarray(valid, bool), structure=np.ones((3, 3), bool), border_value=False)
    if ok.sum() < 64:
        return None
    kern = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float64)
    return [(img[..., c][ok], np.abs(convolve(img[..., c], kern, mode="nearest")[ok])) for c in range(img.shape[2])]


#: Gaussian sigma per unit of the mean |Laplacian| (sqrt(pi / 2) / the kernel's norm 6) and of the median (1 / (6 x
#: the median of |N(0, 1)|, 0.6745))
MEAN_LAPLACIAN_TO_SIGMA = np.sqrt(np.pi / 2) / 6.0
_MEDIAN_LAPLACIAN_TO_SIGMA = 1.0 / (6.0 * 0.6745)


def estimate_relative_noise(image: np.ndarray, valid: np.ndarray) -> float | None:
    """Relative noise sigma / mean of a linear image over its valid pixels (Immerkaer's Laplacian-difference
    estimator, per channel, averaged); None when too few pixels."""
    parts = laplacian_channels(image, valid)
    if parts is None:
        return None
    rel = [MEAN_LAPLACIAN_TO_SIGMA * float(np.mean(lap)) / float(np.mean(v)) for v, lap in parts if np.mean(v) > 0]
    return float(np.mean(rel)) if rel else None


def estimate_pixel_noise(image: np.ndarray, valid: np.ndarray) -> float | None:
    """Relative noise of a linear image (H, W, C) over its valid pixels (H, W) bool, in ``noise_sigma``'s convention
    (relative to the median positive value, :func:`absolute_noise`): per channel the median |Laplacian| as a
    Gaussian sigma over the channel's median positive value, averaged; None when too few pixels.

    :func:`estimate_relative_noise` takes the mean |Laplacian|, which counts every edge and texture as noise (a
    printed board's squares, shadow edges, an object's outline): on smooth light over an 8-pixel checkerboard it
    reads 9x the noise at 0.5% and 2.8x at 2%, where the median reads the noise (tests/test_noise_estimate.py).
    That inflated reading weights the prior (it stands in for the model error of photographed captures; measured,
    bench/results.md, session 54); this one is the photo's noise, against which the verdict judges the residual."""
    parts = laplacian_channels(image, valid)
    if parts is None:
        return None
    rel = [_MEDIAN_LAPLACIAN_TO_SIGMA * float(np.median(lap)) / float(np.median(v[v > 0]))
           for v, lap in parts if (v > 0).any()]
    return float(np.mean(rel)) if rel else None


def absolute_noise(values: np.ndarray, noise: float) -> float:
    """The absolute noise sigma of a relative one (``noise_sigma``'s convention: relative to the median positive
    value of ``values``, any shape); the median taken as 1 when no value is positive."""
    pos = np.asarray(values)[np.asarray(values) > 0]
    return noise * (float(np.median(pos)) if pos.size else 1.0)


def choose_columns(texel_index: np.ndarray, norms: np.ndarray, n: int, env_height: int,
                   spread_order: bool = False) -> np.ndarray:
    """Up to n kept texels spread over the sphere: farthest-point sampling of their directions, starting from the
    column with the most energy. Returns positions into ``texel_index``, sorted (``spread_order``: in the order
    they were picked, so that every prefix is itself spread over the sphere: :func:`measure` may stop early)."""
    n = min(n, texel_index.size)
    if n == 0:
        return np.zeros(0, np.int64)
    d = EnvGrid(env_height).directions().reshape(-1, 3)[texel_index]
    chosen = [int(np.argmax(norms))]
    dist = 1.0 - d @ d[chosen[0]]
    for _ in range(n - 1):
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, 1.0 - d @ d[i])
    return np.array(chosen if spread_order else sorted(chosen), dtype=np.int64)


#: the indirect light is modelled when its chi-squared effect exceeds this many standard deviations of the
#: chi-squared of M independent pixel values (sqrt(2 M)): a shift a fit could tell from noise at 3 sigma
AUTO_EFFECT_Z = 3.0


def indirect_effect(direct: np.ndarray, indirect: np.ndarray, noise: float) -> tuple[float, float]:
    """(chi-squared effect, threshold) of leaving the indirect image out of the model.

    direct, indirect: (M, 3) images of the same lighting (the sampled columns' sum); noise: the target's relative
    noise per fitted pixel (sigma over the median pixel, as ``noise_sigma``). The effect is ``||indirect||^2 /
    sigma_abs^2`` with ``sigma_abs = noise x median(direct > 0)``; the threshold ``AUTO_EFFECT_Z sqrt(2 M)`` over
    the M pixel values.
    """
    if not np.any(direct > 0) or noise <= 0:
        return 0.0, float("inf")
    sigma_abs = absolute_noise(direct, noise)
    effect = float(np.sum(np.asarray(indirect, np.float64) ** 2) / sigma_abs**2)
    return effect, AUTO_EFFECT_Z * float(np.sqrt(2.0 * direct.size))


def pinned_scale_effect(direct: np.ndarray, indirect: np.ndarray, noise: float,
                        pins: np.ndarray) -> tuple[float, float]:
    """(squared z, threshold) of the bias the indirect light puts on an unknown albedo's scale when pixels of known
    albedo (``pins`` (M,) bool) fix it: without the indirect light the known pixels look too dark by
    ``b = sum(p I) / sum(p^2)`` (p the direct image there), which the joint solve passes on to the envmap's scale
    and every unknown albedo; the scale's own noise is ``sigma_abs / sqrt(sum(p^2))``. A bias of a few percent
    hides in the whole image's chi-squared (the known pixels are few) but shifts every albedo (issue 29: a dark
    object on a bright support, 7-26% of its light thrown by the support). Returns ((b / sigma_c)^2,
    AUTO_EFFECT_Z^2); (0, inf) without pins."""
    pins = np.asarray(pins, bool)
    if not pins.any() or pins.all() or noise <= 0:
        return 0.0, float("inf")
    p, i = np.asarray(direct, np.float64)[pins], np.asarray(indirect, np.float64)[pins]
    pp = float(np.sum(p * p))
    if pp <= 0 or not np.any(direct > 0):
        return 0.0, float("inf")
    b = float(np.sum(p * i)) / pp
    sigma_c = absolute_noise(direct, noise) / np.sqrt(pp)
    return (b / sigma_c) ** 2, AUTO_EFFECT_Z**2


@dataclass
class AutoReport:
    relative_indirect: float  # ||sum_s indirect_s|| / ||sum_s direct_s|| over the sampled columns, noise-corrected
    measurement_noise: float  # relative MC noise of that measurement
    per_column_median: float  # median over the sampled columns of the same ratio
    target_noise: float  # relative noise per fitted pixel
    noise_source: str
    columns: int
    choice: str  # "direct" or "direct+indirect"
    effect_chi2: float = 0.0  # leaving the indirect light out: its chi-squared effect (indirect_effect)
    threshold_chi2: float = 0.0  # ... and the threshold it is compared with
    seconds: float = 0.0
    pinned_effect: float = 0.0  # (scale bias / its noise)^2 where known pixels pin an unknown albedo's scale
    pinned_threshold: float = float("inf")
    margins: list | None = None  # the margin after each column from min_columns on (measure's early stop)

    @property
    def margin(self) -> float:
        """The larger of effect / threshold over both tests (the whole fit, the pinned scale): > 1 models the
        indirect light; near 1 the choice is close."""
        fit = self.effect_chi2 / self.threshold_chi2 if self.threshold_chi2 > 0 else 0.0
        pin = self.pinned_effect / self.pinned_threshold if np.isfinite(self.pinned_threshold) else 0.0
        return max(fit, pin)

    def metrics(self) -> dict:
        return {"auto_relative_indirect": round(self.relative_indirect, 6),
                "auto_measurement_noise": round(self.measurement_noise, 6),
                "auto_per_column_median": round(self.per_column_median, 6),
                "auto_target_noise": round(self.target_noise, 6), "auto_noise_source": self.noise_source,
                "auto_effect_chi2": round(self.effect_chi2, 3), "auto_threshold_chi2": round(self.threshold_chi2, 3),
                "auto_margin": round(self.margin, 4),
                **({"auto_pinned_scale_z2": round(self.pinned_effect, 3)} if np.isfinite(self.pinned_threshold)
                   else {}),
                "auto_columns": self.columns, "auto_choice": self.choice, "auto_seconds": round(self.seconds, 3),
                **({"auto_margins": [round(float(m), 3) for m in self.margins]} if self.margins else {})}


def to_rgb(cols: np.ndarray) -> np.ndarray:
    """(C, M, S) -> (M, 3, S)."""
    return np.repeat(cols, 3, axis=0).transpose(1, 0, 2) if cols.shape[0] == 1 else cols.transpose(1, 0, 2)


def indirect_render(pr: PathRenderer, env: np.ndarray, spp: int, max_depth: int, seed: int, scale: int,
                    detail: np.ndarray | None = None, detail_spp: int | None = None) -> np.ndarray:
    """(M, 3) radiance of paths with >= 2 bounces: render(max_depth) - render(2), same seed (``detail``: see
    :meth:`PathRenderer.render`)."""
    full = pr.render(env, spp, max_depth, seed, scale=scale, detail=detail, detail_spp=detail_spp)
    direct = pr.render(env, spp, 2, seed, scale=scale, detail=detail, detail_spp=detail_spp)
    return full - direct


def detail_pixels(object_fraction: np.ndarray, pixel_index: np.ndarray, shape: tuple[int, int],
                  radius: int) -> np.ndarray:
    """(M,) bool: kept pixels within ``radius`` pooled pixels of a pixel that sees the object. There the indirect
    light changes abruptly (the object is lit from below by the support, the support beside the object by the
    object), so the correction is rendered per pixel there instead of interpolated from a coarse image."""
    from scipy.ndimage import binary_dilation

    if radius < 0:
        return np.zeros(pixel_index.shape, bool)
    img = np.zeros(shape[0] * shape[1], bool)
    img[pixel_index[object_fraction > 0]] = True
    img = img.reshape(shape)
    if radius > 0:
        img = binary_dilation(img, structure=np.ones((2 * radius + 1, 2 * radius + 1), bool))
    return img.reshape(-1)[pixel_index]


#: :func:`measure` stops once the decision is this far from its threshold: margin >= AUTO_STOP_MARGIN or
#: <= 1 / AUTO_STOP_MARGIN, after at least AUTO_MIN_COLUMNS columns. Measured (the margin after each column on the
#: demo, the GI bench capture and seven hard-suite captures): after 4 columns the margin was up to 85x the
#: 16-column one (bunny-el20-light: 665,210 against 7,804; the drop came with the 6th column each time, likely a
#: direction that lights much of the support and so raises the median pixel the noise is scaled by), after 6 at
#: most 4.2x above it and 1.5x below; 100 keeps a 24x safety factor over that (bench/results.md, issue 25 session
#: 19)
AUTO_STOP_MARGIN = 100.0
AUTO_MIN_COLUMNS = 6


def _decide(dsum: np.ndarray, ia: np.ndarray, ib: np.ndarray, target_noise: float,
            pins: np.ndarray | None) -> tuple[float, float, float, float, float, float, str]:
    """The decision from the columns measured so far: dsum (M, 3) their direct light summed, ia / ib (M, 3) their
    indirect light summed over the two half renders. Returns (relative indirect, its measurement noise, effect,
    threshold, pinned effect, pinned threshold, choice)."""
    dn = np.linalg.norm(dsum)
    mean = 0.5 * (ia + ib)
    noise2 = np.sum((ia - ib) ** 2) / 4
    bias2 = max(np.sum(mean**2) - noise2, 0.0)
    rel = float(np.sqrt(bias2) / dn) if dn > 0 else 0.0
    noise = float(np.sqrt(noise2) / dn) if dn > 0 else 0.0
    # the indirect image of the sampled columns' lighting, its Monte Carlo noise removed: scaled to the
    # noise-corrected norm (the raw mean's norm includes the measurement's own noise)
    raw = float(np.linalg.norm(mean))
    indirect = mean * (np.sqrt(bias2) / raw if raw > 0 else 0.0)
    effect, threshold = indirect_effect(dsum, indirect, target_noise)
    pin, pin_thr = (0.0, float("inf")) if pins is None else pinned_scale_effect(dsum, indirect, target_noise, pins)
    choice = "direct+indirect" if effect > threshold or pin > pin_thr else "direct"
    return rel, noise, effect, threshold, pin, pin_thr, choice


def measure(pr: PathRenderer, direct_cols, texels: np.ndarray, spp: int, max_depth: int, seed: int,
            scale: int, target_noise: float, noise_source: str, pins: np.ndarray | None = None,
            seeds: np.ndarray | None = None, stop_margin: float | None = None,
            min_columns: int = AUTO_MIN_COLUMNS) -> AutoReport:
    """Measure the indirect light of columns ``texels`` against their direct light and decide by its effect on
    the fit (:func:`indirect_effect`) at ``target_noise`` (relative, per fitted pixel).

    direct_cols: (C, M, S) float32, or a callable texels (B,) -> (C, M, B) (then computed as they are needed).
    The columns are measured in the order given; ``seeds`` (S,) ints: each column's render index (its seeds),
    default its position. ``stop_margin``: stop after ``min_columns`` or more columns once the margin is beyond
    ``stop_margin`` or below its inverse (None: measure every column)."""
    import time

    t0 = time.perf_counter()
    texels = np.asarray(texels, np.int64)
    idx = np.arange(texels.size) if seeds is None else np.asarray(seeds, np.int64)
    half = max(1, spp // 2)
    dsum = ia = ib = None
    per: list[float] = []
    margins: list[float] = []
    d = None
    done = 0
    for s, j in enumerate(bar(texels, desc="auto: indirect", unit="col")):
        if d is None or s >= done:  # direct light of the next columns: the first min_columns at once, then one
            n_next = max(1, min_columns) if s == 0 else 1
            if callable(direct_cols):
                d = to_rgb(direct_cols(texels[s:s + n_next])).astype(np.float64)
            else:
                d = to_rgb(direct_cols[:, :, s:s + n_next]).astype(np.float64)
            first, done = s, s + d.shape[2]
        dcol = d[:, :, s - first]
        env = pr.onehot([int(j)])
        a = indirect_render(pr, env, half, max_depth, seed * 7919 + 2 * int(idx[s]), scale)
        b = indirect_render(pr, env, half, max_depth, seed * 7919 + 2 * int(idx[s]) + 1, scale)
        if dsum is None:
            dsum, ia, ib = np.zeros(dcol.shape), np.zeros(a.shape), np.zeros(b.shape)
        dsum += dcol
        ia += a
        ib += b
        m, nz = 0.5 * (a + b), np.linalg.norm(dcol)
        if nz > 0:
            bias2 = np.sum(m**2) - np.sum((a - b) ** 2) / 4
            per.append(np.sqrt(max(bias2, 0.0)) / nz)
        if stop_margin is not None and s + 1 >= min_columns and s + 1 < texels.size:
            _, _, effect, threshold, pin, pin_thr, _ = _decide(dsum, ia, ib, target_noise, pins)
            r = AutoReport(0.0, 0.0, 0.0, 0.0, "", 0, "", effect, threshold, 0.0, pin, pin_thr)
            margins.append(r.margin)
            if r.margin >= stop_margin or r.margin <= 1.0 / stop_margin:
                texels = texels[: s + 1]
                break
    if dsum is None:
        return AutoReport(0.0, 0.0, 0.0, float(target_noise), noise_source, 0, "direct")
    rel, noise, effect, threshold, pin, pin_thr, choice = _decide(dsum, ia, ib, target_noise, pins)
    return AutoReport(rel, noise, float(np.median(per)) if per else 0.0, float(target_noise), noise_source,
                      int(len(texels)), choice, effect, threshold, time.perf_counter() - t0, pin, pin_thr, margins)


class IndirectCorrection:
    """Indirect light per kept texel from coarse renders of g x g texel blocks (see the module docstring).

    Each rendered block gives the indirect response per unit solid angle at its centre; a texel's correction is
    its solid angle times the bilinear interpolation (in theta, phi; wrapping in phi) of those responses, with
    weights renormalised over the blocks that were rendered (those holding a kept texel).
    """

    def __init__(self, pr: PathRenderer, texel_index: np.ndarray, env_height: int, block: int, spp: int,
                 max_depth: int, seed: int, scale: int, detail: np.ndarray | None = None,
                 detail_spp: int | None = None):
        self.pr = pr
        self.detail, self.detail_spp = detail, detail_spp
        self.grid = EnvGrid(env_height)
        self.texel_index = np.asarray(texel_index, dtype=np.int64)
        self.g = max(1, int(block))
        self.spp, self.max_depth, self.seed, self.scale = spp, max_depth, seed, scale
        h, w = self.grid.height, self.grid.width
        self.hc, self.wc = -(-h // self.g), -(-w // self.g)
        rows_all, cols_all = np.divmod(np.arange(self.grid.n_texels), w)
        self.block_all = (rows_all // self.g) * self.wc + (cols_all // self.g)
        measure = self.grid.solid_angles().ravel()
        self.block_omega = np.bincount(self.block_all, weights=measure, minlength=self.hc * self.wc)
        self.omega = measure[self.texel_index]
        self.blocks = np.unique(self.block_all[self.texel_index])
        self.rendered = np.zeros(self.hc * self.wc, bool)
        self.rendered[self.blocks] = True
        # bilinear weights of every kept texel over the coarse block centres (theta and phi in block units)
        r, c = np.divmod(self.texel_index, w)
        y = (r + 0.5) / self.g - 0.5
        x = (c + 0.5) / self.g - 0.5
        y0 = np.floor(y).astype(np.int64)
        x0 = np.floor(x).astype(np.int64)
        fy, fx = y - y0, x - x0
        nb, wt = [], []
        # never interpolate across the horizon (the support plane makes light there discontinuous): with g
        # dividing H/2, block rows < hc/2 lie above it
        own_row = r // self.g
        split = self.hc // 2 if (h // 2) % self.g == 0 else None
        for dy, wy in ((0, 1 - fy), (1, fy)):
            yy = np.clip(y0 + dy, 0, self.hc - 1)
            if split is not None:
                yy = np.where((yy < split) != (own_row < split), own_row, yy)
            for dx, wx in ((0, 1 - fx), (1, fx)):
                xx = np.mod(x0 + dx, self.wc)
                nb.append(yy * self.wc + xx)
                wt.append(wy * wx)
        nb, wt = np.stack(nb, 1), np.stack(wt, 1)
        wt = wt * self.rendered[nb]
        tot = wt.sum(axis=1, keepdims=True)
        own = self.block_all[self.texel_index]
        lone = tot[:, 0] <= 1e-12  # no rendered neighbour with weight: use the texel's own block
        wt = np.where(lone[:, None], 0.0, wt / np.maximum(tot, 1e-12))
        nb[lone, 0], wt[lone, 0] = own[lone], 1.0
        self.nb, self.wt = nb, wt
        self._cache: dict[int, np.ndarray] = {}
        self.renders = 0

    def compute_all(self) -> None:
        for b in bar(self.blocks, desc="auto: indirect correction", unit="block"):
            self._block(int(b))

    def _block(self, b: int) -> np.ndarray:
        """(M, 3) indirect response per unit solid angle of block b."""
        if b not in self._cache:
            texels = np.nonzero(self.block_all == b)[0]
            env = self.pr.onehot(texels)
            d = indirect_render(self.pr, env, self.spp, self.max_depth, self.seed * 104729 + b, self.scale,
                                self.detail, self.detail_spp)
            self._cache[b] = (d / self.block_omega[b]).astype(np.float32)
            self.renders += 2
        return self._cache[b]

    def columns(self, a: int, b: int, channels: int) -> np.ndarray:
        """(C, M, b - a) indirect light of kept texels a .. b - 1 (positions into texel_index)."""
        cols = []
        for i in range(a, b):
            acc = None
            for nb, wt in zip(self.nb[i], self.wt[i]):
                if wt > 0:
                    v = self._block(int(nb)) * float(wt)
                    acc = v if acc is None else acc + v
            cols.append(acc * float(self.omega[i]))
        out = np.stack(cols, axis=2)  # (M, 3, B)
        if channels == 1:
            return out.mean(axis=1)[None]
        return out.transpose(1, 0, 2)
