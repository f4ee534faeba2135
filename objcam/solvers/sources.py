"""Compact sources where the data cannot place them (issue 22, ``solve.sources=compact``).

The edge-preserving prior (objcam.solvers.edges) charges a bright blob less the wider it is, so a small lamp the
photo cannot place to within a texel or two comes back spread over a band of rows: in the tonemapped map a wide
band saturates and the sky beside it is dimmed. This step asks the data, after the solve, whether they can tell
the blob from a point source:

1. blobs: connected texels (8-neighbours, the azimuth wrapping) whose luminance exceeds ``BRIGHT_FACTOR`` x the
   map's median;
2. for each blob, brightest first: the blob's texels set to the rim's median (the sky around it), and the energy
   put back in the one texel of the blob, or the two, that fit the data best (per channel, amplitudes by
   non-negative least squares against the residual);
3. kept when the fit's sum of squared residuals rises by less than its own spread, sqrt(2 / M) x the fit's sum
   of squares (M fitted values: chi-squared of M values, unit variance, has spread sqrt(2 M)); the rise is
   counted from the solve's own fit, over every blob collapsed so far.

The rest of the map stays as solved. (Solving it again on the data less the point sources, with the solver's
own prior, was measured and dropped: without the bright source the edge prior's scale keeps the dim sky's noise,
and lamp3_r0 on the hard suite fell from SSIM 0.89 to 0.44; bench/results.md, issue 22, session 20.)

A blob the data do place (collapsing it raises the misfit past its spread) is left as the solve made it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import numpy as np
from scipy import ndimage

from objcam.envmap import EnvGrid

# a texel an order of magnitude above the map's median is a source candidate: the hard suite's lamps and suns
# are 1e2-1e5 x their sky, an HDRI's bright clouds a few x (the test of step 3 decides; this only bounds the work)
BRIGHT_FACTOR = 10.0
MAX_BLOBS = 6  # the brightest blobs tried (the suite's rooms have 5 lamps)


@dataclass
class SourcesResult:
    """The map after the step and its record for solve.json."""

    x: np.ndarray  # (N, 3)
    info: dict = field(default_factory=dict)


def bright_blobs(lum: np.ndarray, grid: EnvGrid, texel_index: np.ndarray, factor: float = BRIGHT_FACTOR
                 ) -> list[np.ndarray]:
    """Connected bright texels of ``lum`` (N,) (luminance at A's texels ``texel_index``, flat indices into the
    lat-long ``grid``): texels above ``factor`` x the median of the positive ones, 8-connected with the azimuth
    wrapping. Returns the blobs as arrays of positions into the N texels, in label order."""
    pos = lum[lum > 0]
    if pos.size == 0:
        return []
    bright = lum > factor * float(np.median(pos))
    if not bright.any():
        return []
    img = np.zeros(grid.n_texels, bool)
    img[texel_index[bright]] = True
    img = img.reshape(grid.shape)
    lab, n = ndimage.label(img, structure=np.ones((3, 3), int))
    # the azimuth wraps: a blob across the seam is one blob
    parent = np.arange(n + 1)

    def root(a: int) -> int:
        while parent[a] != a:
            a = parent[a]
        return a

    H, W = grid.shape
    for r in range(H):
        for dr in (-1, 0, 1):
            r2 = r + dr
            if 0 <= r2 < H and lab[r, W - 1] and lab[r2, 0]:
                a, b = root(lab[r, W - 1]), root(lab[r2, 0])
                parent[max(a, b)] = min(a, b)
    flat = lab.reshape(-1)[texel_index]
    roots = np.array([root(v) if v else 0 for v in flat])
    return [np.flatnonzero(roots == v) for v in np.unique(roots[roots > 0])]


def rim_of(blob: np.ndarray, grid: EnvGrid, texel_index: np.ndarray, exclude: np.ndarray) -> np.ndarray:
    """Positions (into the N texels) of the texels 8-adjacent to ``blob`` (azimuth wrapping), not in ``exclude``
    (N,) bool."""
    H, W = grid.shape
    img = np.zeros(grid.n_texels, bool)
    img[texel_index[blob]] = True
    img = img.reshape(H, W)
    wrapped = np.concatenate([img[:, -1:], img, img[:, :1]], axis=1)
    grown = ndimage.binary_dilation(wrapped, structure=np.ones((3, 3), bool))[:, 1:-1]
    ring = grown.reshape(-1)[texel_index] & ~exclude
    return np.flatnonzero(ring)


def fit_residual(A, use: np.ndarray, Y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, float]:
    """(residual (M_use, 3), its sum of squares) of the map z (N, 3) on A (C, M, N) against Y (M_use, 3), the
    target at the usable rows ``use`` (M,) bool; float32 products, as the solve's own prediction."""
    pred = np.stack([np.asarray(A[0 if A.shape[0] == 1 else c] @ z[:, c].astype(np.float32), np.float64)
                     for c in range(3)], axis=1)[use]
    r = Y - pred
    return r, float(np.sum(r * r))


def _columns(A: np.ndarray, use: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(C, M_use, K) float64 columns ``cols`` of A (C, M, N) at the usable rows."""
    return np.stack([np.asarray(A[c][:, cols], np.float64)[use] for c in range(A.shape[0])])


def _fit(cols: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, float]:
    """Non-negative amplitudes (K, 3) of the columns ``cols`` (C, M, K) that best fit the residual r (M, 3), and
    the sum of squares left. K is 1 or 2: the 2-column problem by its active sets."""
    K = cols.shape[2]
    amp = np.zeros((K, 3))
    left = 0.0
    for ch in range(3):
        a = cols[0 if cols.shape[0] == 1 else ch]
        G, b = a.T @ a, a.T @ r[:, ch]
        best, best_cost = np.zeros(K), float(r[:, ch] @ r[:, ch])
        cands = [np.linalg.solve(G, b)] if K == 2 and abs(np.linalg.det(G)) > 1e-12 * np.trace(G) ** 2 else []
        cands += [np.where(np.arange(K) == k, b[k] / G[k, k], 0.0) for k in range(K) if G[k, k] > 0]
        for z in cands:
            if (z >= 0).all():
                cost = float(r[:, ch] @ r[:, ch] - 2 * z @ b + z @ G @ z)
                if cost < best_cost:
                    best, best_cost = z, cost
        amp[:, ch] = best
        left += best_cost
    return amp, left


def compact_sources(A: np.ndarray, use: np.ndarray, y: np.ndarray, x: np.ndarray, grid: EnvGrid,
                    texel_index: np.ndarray, factor: float = BRIGHT_FACTOR,
                    max_blobs: int = MAX_BLOBS) -> SourcesResult:
    """The step of the module docstring. A (C, M, N) the transport (C = 1: grey, or 3), ``use`` (M,) bool the
    fitted rows, y (M, 3) the target at A's rows, x (N, 3) the solve's map at A's texels ``texel_index`` in
    ``grid``. Returns the map and the record (blobs found, collapsed, the misfit's change against its
    spread)."""
    x = np.asarray(x, np.float64)
    Y = np.asarray(y, np.float64)[use]

    r0, ss0 = fit_residual(A, use, Y, x)
    m = int(Y.size)
    tol = float(np.sqrt(2.0 / max(m, 1)) * ss0)  # the chi-squared's spread, in the fit's own units
    lum = x.mean(axis=1)
    blobs = bright_blobs(lum, grid, texel_index, factor)
    energy = [float(lum[b].sum()) for b in blobs]
    order = np.argsort(energy)[::-1][:max_blobs]
    bright = np.zeros(lum.size, bool)
    for b in blobs:
        bright[b] = True
    info: dict = {"mode": "compact", "bright_factor": factor, "blobs_found": len(blobs), "fitted_values": m,
                  "ss_fit": ss0, "ss_spread": tol, "blobs": []}
    cur, r, ss = x.copy(), r0, ss0
    for i in order:
        blob = blobs[i]
        rim = rim_of(blob, grid, texel_index, bright)
        sky = np.median(cur[rim], axis=0) if rim.size else np.zeros(3)
        base = cur.copy()
        base[blob] = sky
        cols = _columns(A, use, blob)  # (C, M_use, K)
        delta = cur[blob] - sky[None, :]  # (K, 3): the blob's energy above its sky
        rb = r + np.stack([cols[0 if cols.shape[0] == 1 else c] @ delta[:, c] for c in range(3)], axis=1)
        fits = [(_fit(cols[:, :, [k]], rb), (k,)) for k in range(blob.size)]
        (amp1, ss1), k1 = min(fits, key=lambda f: f[0][1])
        choice, amp, ss_new = k1, amp1, ss1
        if ss1 - ss0 > tol and blob.size > 1:  # two texels: the best one and a partner in the blob
            pairs = [(_fit(cols[:, :, [k1[0], k]], rb), (k1[0], k)) for k in range(blob.size) if k != k1[0]]
            (amp2, ss2), k2 = min(pairs, key=lambda f: f[0][1])
            if ss2 < ss1:
                choice, amp, ss_new = k2, amp2, ss2
        rec = {"texels": int(blob.size), "peak": float(lum[blob].max()), "sky": float(sky.mean()),
               "rise": float(ss_new - ss0), "kept_to": len(choice)}
        if ss_new - ss0 <= tol:
            cur = base
            for j, k in enumerate(choice):
                cur[blob[k]] += amp[j]
            r, ss = fit_residual(A, use, Y, cur)
            rec["collapsed"] = True
        else:
            rec["collapsed"] = False
        info["blobs"].append(rec)
    info["collapsed"] = sum(b["collapsed"] for b in info["blobs"])
    info["ss_after"] = ss
    info["rise_over_spread"] = float((ss - ss0) / tol) if tol > 0 else 0.0
    return SourcesResult(cur, info)
