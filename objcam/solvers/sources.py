"""Compact sources the photo places better than the prior's spread (issues 22 and 28, ``solve.sources``).

The edge-preserving prior (objcam.solvers.edges) charges a bright blob less the wider it is, so a small lamp comes
back spread over a band of rows even where the photo places it: lamp30_r0_n2 of the hard suite, a 2-degree lamp
at 30 deg, came back over five rows at a tenth of its peak, the band below it at 3.6 x the truth's energy, while
the same energy in the lamp's own texel fits the photo with chi-squared 3.9 against the spread map's 7.3 (and
the truth's 4.7). This step, after the solve and its sky profile, asks the photo where each blob's light is:

1. blobs: connected texels (8-neighbours, the azimuth wrapping) whose luminance exceeds ``BRIGHT_FACTOR`` x the
   map's median; at most ``MAX_BLOBS``, the most energy (luminance x solid angle) first;
2. for each blob: the light above the sky around it (the rim's median), per channel, moved whole into the one
   texel of the blob that fits the photo best (a source inside a texel: the texel's area average), or, where
   that fits worse by the fall step 3 asks, split between that texel and a neighbour of it (centres within
   ``NEIGHBOUR_TEXELS`` texel heights) at the share that fits best (a source across two). The light is moved,
   never made: an amplitude fitted freely to the residual also fits what the model lacks elsewhere (a
   courtyard's dim 9-texel patch took 20 x its own energy that way);
3. kept when the fit's sum of squared residuals *falls* by at least ``FALL_SHARE`` of what the map misfits
   beyond the noise (:func:`misfit_allowance`, also step 3b's of objcam.solvers.skyprofile: the larger of the
   chi-squared's spread ``sqrt(2 / M)`` x the sum of squares and its excess over the stated noise), counted from
   the fit with the blobs moved so far, and the photo places it: every texel of the blob that is not a
   neighbour of the chosen one fits worse, alone, by at least as much (the texels tried: the blob's
   ``MAX_CANDIDATES`` brightest). The photo must prefer the point by a share of the misfit that model error
   could move: a point that fits only a little better may be fitting what the model lacks (a bright patch of a
   courtyard's wall, moved on a fall of a seventh of that misfit, became the map's brightest texel, 150 deg
   from the sun). And it must say where: a lamp 1 deg above the horizon, smeared along it, fitted about as well
   in texels 12 columns apart, and a split between them put the larger share on the wrong side.

The rest of the map stays as solved. (Solving it again on the data less the point sources, with the solver's
own prior, was measured and dropped: without the bright source the edge prior's scale keeps the dim sky's noise,
and lamp3_r0 on the hard suite fell from SSIM 0.89 to 0.44; bench/results.md, issue 22, session 20. The rule of
sessions 20-34, off by default then: collapse where the misfit rises by less than its spread, with amplitudes
fitted freely; it collapsed extended sources the photo cannot resolve, courtyard's sun area among them, with
brightest-source errors of 138-155 deg.)
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
# the share of the map's misfit beyond the noise a point must take away to be kept (step 3), a round value above
# the falls that hurt on the hard suite (a courtyard's lit patches: 0.14 of it; the lamps that gained: 0.25-0.70;
# bench/results.md, issues 22 and 28, session 43)
FALL_SHARE = 0.2
# a texel's neighbours: centres within 1.5 texel heights (the diagonal neighbour at the equator is 1.41 away)
NEIGHBOUR_TEXELS = 1.5
# the texels of a blob its light may move to: its brightest (a courtyard's lit façade, 306 texels, cost 45 ms for
# all; the suite's lamps' blobs are 2-92 texels, their own texel among the brightest few)
MAX_CANDIDATES = 48


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
    z32 = np.asarray(z, np.float32)
    if A.shape[0] == 1:  # one product for the three channels of a grey A
        pred = np.asarray(A[0] @ z32, np.float64)[use]
    else:
        pred = np.stack([np.asarray(A[c] @ z32[:, c], np.float64) for c in range(3)], axis=1)[use]
    r = Y - pred
    return r, float(np.sum(r * r))


def misfit_allowance(ss_map: float, values: int, sigma_abs: float | None) -> tuple[float, float]:
    """(allowed rise of the sum of squares, the map's excess) of objcam.solvers.skyprofile's step 3b (and the
    misfit this module's step 3 takes a share of): the larger of the spread ``sqrt(2 /
    values) x ss_map`` and the excess ``ss_map - values x sigma_abs^2`` (0 when negative): the part of the solved
    map's sum of squared residuals ``ss_map`` over ``values`` fitted pixel values that honest noise of
    ``sigma_abs`` per value cannot account for even unfitted, a lower bound of the model error the map carries
    (a fit also absorbs some noise, so the model error can be larger; the bound keeps the step conservative).
    sigma_abs None (noise unknown): the spread."""
    spread = float(np.sqrt(2.0 / max(values, 1)) * ss_map)
    if not sigma_abs or values <= 0:
        return spread, 0.0
    excess = max(float(ss_map) - values * float(sigma_abs) ** 2, 0.0)
    return max(spread, excess), excess


def _columns(A: np.ndarray, use: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(C, M_use, K) float64 columns ``cols`` of A (C, M, N) at the usable rows."""
    out = np.empty((A.shape[0], int(np.count_nonzero(use)), len(cols)))
    for c in range(A.shape[0]):
        # np.take gathers the columns row by row (a fancy index on axis 1 is ~8 x slower on a (16384, 1088) A);
        # the float64 cast happens in the assignment, with no further copy
        out[c] = np.take(A[c], cols, axis=1)[use]
    return out


def _moved(cols: np.ndarray, rb: np.ndarray, energy: np.ndarray, omega: np.ndarray, need: float,
           dirs: np.ndarray, reach: float) -> tuple[float, tuple, np.ndarray, float]:
    """Where the blob's ``energy`` (3,) (radiance x sr per channel, above its sky) fits the residual ``rb``
    (M, 3) best (the blob's own light taken out of the fit): in one of its K texels (columns ``cols`` (C, M, K),
    solid angles ``omega`` (K,) sr), or, where that fits worse by at least ``need`` (sum of squares), split
    between the best one and a neighbour of it (its centre within ``reach`` radians of the best one's; ``dirs``
    (K, 3) the texels' unit directions) at the best share. Returns (the sum of squares left, the texels'
    positions in the blob, their radiance (len, 3), the margin: how much worse the best texel that is not a
    neighbour of the chosen one fits, inf where there is none). One texel is the area average of a source
    inside it; a split is a source across two, taken only where the photo says so (two texels apart it would be
    two sources: a lamp 1 deg above the horizon, smeared along it, was split 12 columns apart, the larger share
    on the wrong side)."""
    K = cols.shape[2]
    grey = cols.shape[0] == 1  # one column set for the three channels: each product once
    amp = energy[None, :] / omega[:, None]  # (K, 3): the whole energy in texel k
    base = float(np.sum(rb * rb))
    if grey:
        proj = cols[0].T @ rb  # (K, 3)
        norm = np.repeat(np.einsum("mk,mk->k", cols[0], cols[0])[:, None], 3, axis=1)  # (K, 3)
    else:
        proj = np.stack([cols[c].T @ rb[:, c] for c in range(3)], axis=1)
        norm = np.stack([np.einsum("mk,mk->k", cols[c], cols[c]) for c in range(3)], axis=1)
    one = base - np.sum(2 * amp * proj - amp * amp * norm, axis=1)  # (K,)
    k1 = int(np.argmin(one))
    best = (float(one[k1]), (k1,), amp[[k1]])
    far = dirs @ dirs[k1] < np.cos(reach)  # (K,): not k1's neighbours (in angle: near the pole a row is narrow)
    margin = float(one[far].min() - one[k1]) if far.any() else np.inf
    if K == 1:
        return best + (margin,)
    # a share t in texel k1, 1 - t in texel k: the residual c - t w with c = rb - v_k, w = u - v_k (u, v_k the
    # whole energy in k1, in k), so the best share is (c . w) / (w . w), clipped to [0, 1], summed over channels
    if grey:  # (K, 3): a_k . a_k1
        cross = np.repeat((cols[0].T @ cols[0][:, k1])[:, None], 3, axis=1)
    else:
        cross = np.stack([cols[c].T @ cols[c][:, k1] for c in range(3)], axis=1)
    u_u, u_rb = amp[k1] ** 2 * norm[k1], amp[k1] * proj[k1]  # (3,)
    v_v, v_rb, u_v = amp ** 2 * norm, amp * proj, amp[k1][None, :] * amp * cross  # (K, 3)
    c_w = (u_rb[None, :] - v_rb) - (u_v - v_v)  # (rb - v) . (u - v)
    w_w = u_u[None, :] - 2 * u_v + v_v
    t = np.clip(c_w.sum(axis=1) / np.maximum(w_w.sum(axis=1), 1e-300), 0.0, 1.0)  # (K,)
    c_c = base - 2 * v_rb.sum(axis=1) + v_v.sum(axis=1)
    two = c_c - 2 * t * c_w.sum(axis=1) + t * t * w_w.sum(axis=1)
    two[far] = np.inf
    two[k1] = np.inf
    k2 = int(np.argmin(two))
    if two[k2] <= best[0] - need:
        best = (float(two[k2]), (k1, k2), np.stack([t[k2] * amp[k1], (1 - t[k2]) * amp[k2]]))
    return best + (margin,)


def compact_sources(A: np.ndarray, use: np.ndarray, y: np.ndarray, x: np.ndarray, grid: EnvGrid,
                    texel_index: np.ndarray, omega: np.ndarray, sigma_abs: float | None,
                    factor: float = BRIGHT_FACTOR, max_blobs: int = MAX_BLOBS,
                    fall_share: float = FALL_SHARE) -> SourcesResult:
    """The step of the module docstring. A (C, M, N) the transport (C = 1: grey, or 3), ``use`` (M,) bool the
    rows to fit (the solve passes every usable one), y (M, 3) the target at A's rows, x (N, 3) the solve's map at A's texels ``texel_index`` in
    ``grid`` of solid angles ``omega`` (N,) sr; ``sigma_abs`` the stated noise of one fitted value (None:
    unknown, the spread alone). Returns the map and the record (blobs found, collapsed, the misfit's change)."""
    x = np.asarray(x, np.float64)
    Y = np.asarray(y, np.float64)[use]
    om = np.asarray(omega, np.float64)
    r0, ss0 = fit_residual(A, use, Y, x)
    m = int(Y.size)
    tol = float(np.sqrt(2.0 / max(m, 1)) * ss0)  # the chi-squared's spread, in the fit's own units
    allow, excess = misfit_allowance(ss0, m, sigma_abs)
    need = max(tol, fall_share * allow)
    lum = x.mean(axis=1)
    dirs = grid.directions().reshape(-1, 3)[texel_index]
    blobs = bright_blobs(lum, grid, texel_index, factor)
    energy = [float((lum[b] * om[b]).sum()) for b in blobs]
    order = np.argsort(energy)[::-1][:max_blobs]
    bright = np.zeros(lum.size, bool)
    for b in blobs:
        bright[b] = True
    info: dict = {"mode": "compact", "bright_factor": factor, "blobs_found": len(blobs), "fitted_values": m,
                  "ss_fit": ss0, "ss_spread": tol, "ss_excess": excess, "fall_needed": need, "blobs": []}
    cur, r, ss = x.copy(), r0, ss0
    for i in order:
        blob = blobs[i]
        rim = rim_of(blob, grid, texel_index, bright)
        sky = np.median(cur[rim], axis=0) if rim.size else np.zeros(3)
        delta = np.maximum(cur[blob] - sky[None, :], 0.0)  # (K, 3): the blob's light above its sky
        # where the light may go: the blob's brightest texels (a spread lamp's own texel is among them)
        cand = blob if blob.size <= MAX_CANDIDATES else blob[np.argsort(lum[blob])[::-1][:MAX_CANDIDATES]]
        cols = _columns(A, use, cand)  # (C, M_use, K')
        if cand is blob:  # the fit without the blob's light
            rb = r + (cols[0] @ delta if cols.shape[0] == 1 else
                      np.stack([cols[c] @ delta[:, c] for c in range(3)], axis=1))
        else:
            without = cur.copy()
            without[blob] -= delta
            rb = fit_residual(A, use, Y, without)[0]
        ss_new, choice, amp, margin = _moved(cols, rb, (delta * om[blob, None]).sum(axis=0), om[cand], need,
                                             dirs[cand], NEIGHBOUR_TEXELS * np.pi / grid.height)
        rec = {"texels": int(blob.size), "peak": float(lum[blob].max()), "sky": float(sky.mean()),
               "fall": float(ss - ss_new), "kept_to": len(choice),
               "margin": margin if np.isfinite(margin) else None,  # strict JSON: no texel away from it
               "collapsed": bool(ss - ss_new >= need and margin >= need)}
        if rec["collapsed"]:  # cur is the step's own copy of x
            cur[blob] -= delta
            for j, k in enumerate(choice):
                cur[cand[k]] += amp[j]
            r, ss = fit_residual(A, use, Y, cur)
        info["blobs"].append(rec)
    info["collapsed"] = sum(b["collapsed"] for b in info["blobs"])
    info["ss_after"] = ss
    info["fall_over_needed"] = float((ss0 - ss) / need) if need > 0 else 0.0
    return SourcesResult(cur, info)
