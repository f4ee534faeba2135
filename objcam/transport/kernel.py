"""``transport.texel_kernel``: box texels or a narrow kernel, by the fit (``auto`` and ``fit``).

A column of A is the image of one texel's radiance. With box texels (kernel 1) the shadow rays sample the whole
texel, so a column is the light of a uniformly bright 5.6-deg patch (at 32 x 64) and its shadows have a 5.6-deg
penumbra. A source smaller than a texel (a lamp, the sun) casts sharper shadows than any box column: a fit with
box columns can sharpen a shadow only by negative lobes beside the bright texel, which x >= 0 clips to black (the
black rings of the suite's lamps and rooms, bench/results.md, session 27). A narrow kernel (the rays aim into the
central ``NARROW`` of the texel per side) gives sharp columns; a compact source between two texel centres is then
a non-negative mix of two of them. But under an extended source (a window, an overcast sky) seen past a thin
occluder, narrow columns alias: the sum of sharp shadows is a comb where the photo holds a smooth penumbra.

Neither is right for every sky, and the sky is what the solve finds. So the transport stage solves each target on
the box A (the default solve, objcam.solvers.plan.solve_capture, with its verdict) and tries candidates, each
target keeping the one whose fit leaves the lowest chi-squared per fitted value (the verdict's ``chi2``: the
residual against the stated noise, over the same pixels for every candidate: those every one of them fitted,
:func:`on_common_pixels`; one exception, ``point`` over ``compact``, below):

* ``compact``: the box A with narrow columns at the solve's compact bright blobs only (a lamp, a sun: at most
  ``COMPACT_TEXELS`` texels above ``COMPACT_LEVEL`` x the sky's median, grown by one texel), the rest box texels:
  the narrow and box direct light of those few texels from the box build's own direct model, the indirect part
  kept; cheap (the demo: 24 texels, ~0.5 s);
* ``point``: the box A with each compact source's texel given the direct light of a point where the photo puts
  it inside the texel (objcam.transport.points), the rest box texels;
* ``narrow``: the whole A with the narrow kernel (a second build: the same seeds, so the difference is the kernel,
  not Monte Carlo noise), for the targets whose box solve left more than ``DARK_TRIGGER`` of the sky black
  (``auto``, the default) or for every target (``fit``).

``point`` and ``compact`` answer the same question, where a compact source sits inside its texel: ``point`` by one
column placed by the photo, ``compact`` by narrow columns at each of the blob's texels and its ring, which the
solve may mix. Where both beat box texels, ``point`` is kept even if ``compact`` fits better: the mix reaches its
lower misfit by splitting one source over several texels (the hard suite's lamp 1 deg up, torus-el60-light at
137 deg: three blobs over 39 deg, the brightest 17 deg off; one with ``point``, 2.8 deg), so the better fit is the
model error, not the source. ``narrow`` (a different sky: every shadow sharp) still competes on its fit.

A target whose albedo is unknown shares its camera's A with the other targets of that camera (the joint solve
ties them by the albedo), so there the camera chooses, by the chi-squared summed over its targets; ``auto`` keeps
box texels there, since the joint solve repeated per candidate took a two-photo capture's transport from 10 to 58 s
(``fit`` still asks). Measured on the
hard suite and the core bench's capture: bench/results.md, issue 22, session 28.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from objcam.metrics import LUMA
from objcam.solvers.plan.defaults import VERDICT_DARK_YELLOW

#: the narrow kernel's width, a fraction of the texel per side (0.25: 1.4 deg at 32 x 64, under the 2-deg lamps
#: of the suite; 0.5 recovered less of the rooms, bench/results.md)
NARROW = 0.25
#: ``auto`` builds the narrow A only where the box A's solve left more of the sky black than this (the verdict's
#: yellow line, objcam.solvers.plan.defaults.VERDICT_DARK_YELLOW): on the hard suite 10 of 96 targets, all
#: rooms; no core bench or demo target
DARK_TRIGGER = VERDICT_DARK_YELLOW


#: ``compact``: a blob is the 8-connected texels above COMPACT_LEVEL x the solved sky's median luminance, compact
#: when it has at most COMPACT_TEXELS texels at 32 rows (x (H / 32)^2 on finer grids): a lamp or a sun smeared by
#: the box solve, not a window or an overcast sun area (the suite's windows, courtyard's sun: 150+ texels)
COMPACT_LEVEL = 10.0
COMPACT_TEXELS = 9


def pilot(scene, targets: list, tr, capture: Path) -> dict[str, dict]:
    """{target: {"chi2", "values", "dark_sky_area", "envmap", "mask", "y", "fitted"}} of the default solve of
    ``targets`` on the Transport ``tr`` (the verdict's chi2 per fitted value and its share of black sky,
    objcam.solvers.plan.verdict; the solved (H, W, 3) envmap and its (H, W) mask; the target at A's rows (M, 3)
    and the (M,) pixels the solve fitted). Without solve.sky_profile:
    the pilot judges the A, and the black rings a profile would hide are what asks for the narrow one; without
    solve.noise_fit: every candidate judged at the stated noise's prior (the transport's choice does not depend on
    the solve's later weighting); with the verdict's fit measures only (solve.verdict=fit: its uncertainty and
    resolution are not compared)."""
    from objcam.solvers.plan.capture import solve_capture
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.targets import TargetData
    from objcam.transport.pixels import target_rows

    data = {t.name: TargetData(tr, *target_rows(t.load_image(scene.folder), t.load_valid(scene.folder),
                                                tr.downsample, tr.pixel_index)) for t in targets}
    sols = solve_capture(scene.model_copy(update={"targets": list(targets)}), data,
                         SolveParams(sky_profile="off", noise_fit="off", sources="off", verdict="fit"), capture)
    out = {}
    for t in targets:
        s = sols[t.name]
        v = s.info.get("verdict", {})
        d, rej = data[t.name], s.rejected
        out[t.name] = {"chi2": float(v.get("chi2", np.inf)), "values": int(d.use.sum()) * 3,
                       "dark_sky_area": float(v.get("dark_sky_area", 0.0)), "envmap": s.envmap,
                       "mask": s.mask, "y": d.y, "fitted": d.use if rej is None else d.use & ~rej,
                       "pred": np.asarray(s.prediction, np.float64).reshape(-1, 3)[tr.pixel_index],
                       "noise": float(v.get("noise_per_fitted_pixel", np.nan))}
    return out


def on_common_pixels(results: dict[str, dict[str, dict]], names: list[str]) -> None:
    """Give every candidate's pilot of each target in ``names`` its chi2 per value over the same pixels: those
    every candidate fitted (``fitted``: the solve's usable rows less the outliers it dropped), at the stated noise
    (``results``: candidate -> target -> :func:`pilot`'s result, updated in place: ``chi2``, ``values``; the
    solve's own chi2 over its own pixels kept as ``chi2_own``).

    Each solve drops its own outliers, so their chi2 were over different pixels: box texels that cannot draw a
    lamp's sharp shadow dropped the pixels at its edge, which a point source placed in the texel kept and paid
    for, so box texels won on fewer pixels (the hard suite's lamp 1 deg up on the light torus at 2%: box 7.3,
    point 8.1, each on its own pixels; on box's own pixels the point's map misfits less: 7.1e-4 against 8.5e-4 in
    squares; its brightest source 16.9 -> 1.9 deg off; bench/results.md, issue 22, session 47). The pixels any
    candidate fitted instead charge each candidate at full weight for the pixels it dropped, and the rooms'
    narrow kernel lost to point sources that fit more pixels with a worse map (room2_r251 at 2% 0.95 -> 0.67
    SSIM); the same with a Huber loss beyond the solve's 6 sigma: no different. Measured, not taken."""
    from objcam.transport.auto import absolute_noise

    for n in names:
        have = [r[n] for r in results.values() if n in r]
        rows = np.logical_and.reduce([p["fitted"] for p in have])
        y = np.asarray(have[0]["y"], np.float64)[rows]
        sigma_rel = have[0]["noise"]
        if not rows.any() or not np.isfinite(sigma_rel):
            continue  # nothing to compare on: the solves' own chi2 stand
        sigma_abs = absolute_noise(y, sigma_rel)
        for p in have:
            p["chi2_own"] = p["chi2"]
            p["chi2"] = float(np.mean(((y - p["pred"][rows]) / sigma_abs) ** 2))
            p["values"] = int(rows.sum()) * 3


def triggered(box: dict[str, dict]) -> list[str]:
    """``auto``: the targets whose box solve left more than ``DARK_TRIGGER`` of the sky black (the rings)."""
    return [name for name, p in box.items() if p["dark_sky_area"] > DARK_TRIGGER]


def compact_blobs(envmap: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the compact bright blobs of a solved envmap (H, W, 3) on its solved texels ``mask`` (H, W),
    grown by one texel (a lamp straddles texels); azimuth wraps."""
    from scipy.ndimage import binary_dilation, label

    h, w = mask.shape
    lum = np.where(mask, np.asarray(envmap, np.float64) @ LUMA, 0.0)
    lit = lum[mask & (lum > 0)]
    if lit.size == 0:
        return np.zeros((h, w), bool)
    bright = lum > COMPACT_LEVEL * float(np.median(lit))
    empty = np.flatnonzero(~bright.any(axis=0))
    if empty.size == 0:  # bright all around the horizon: no compact source to find
        return np.zeros((h, w), bool)
    shift = -int(empty[0])  # put a column without bright texels at the seam, so no blob is cut by it
    lab, n = label(np.roll(bright, shift, axis=1), structure=np.ones((3, 3), bool))
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    keep = np.zeros(n + 1, bool)
    keep[1:] = sizes[1:] <= COMPACT_TEXELS * max(1.0, (h / 32) ** 2)
    blobs = np.roll(keep[lab], -shift, axis=1)
    grown = binary_dilation(np.concatenate([blobs[:, -1:], blobs, blobs[:, :1]], axis=1),
                            structure=np.ones((3, 3), bool))[:, 1:-1]
    return grown & mask


@dataclass
class Columns:
    """A candidate A that differs from the box Transport's in a few columns: their positions ``pos`` (B,), their
    new values ``cols`` (C, M, B) float32 and the candidate's whole Gram matrix ``gram`` (C, N, N) float64. Kept
    as columns, not a copy of A (the copies and their first-touch pages were ~1 s of the demo's transport)."""

    pos: np.ndarray
    cols: np.ndarray
    gram: np.ndarray


def compact_columns(tr, direct, texels: np.ndarray) -> Columns:
    """The box Transport ``tr`` with the columns of the grid texels ``texels`` made the narrow kernel's direct
    light (plus the box A's indirect part, which the kernel does not change); ``direct``: the box A's direct-light
    model (objcam.transport.direct.SplitDirect)."""
    import copy

    from objcam.transport.direct import DirectStats, SplitDirect

    pos = np.flatnonzero(np.isin(tr.texel_index, texels))
    tex = tr.texel_index[pos]

    def narrowed(dm):
        c = copy.copy(dm)
        c.kernel, c._dr, c.stats = NARROW, None, DirectStats()
        return c

    narrow = SplitDirect([(rows, narrowed(dm)) for rows, dm in direct.parts], direct.m)
    return replace_direct(tr, pos, narrow.columns(tex) - direct.columns(tex))


def replace_direct(tr, pos: np.ndarray, delta: np.ndarray) -> Columns:
    """The Transport ``tr`` with ``delta`` (C, M, B) added to its columns ``pos`` (B,) (a change of their direct
    light; the indirect part kept), as :class:`Columns` with the Gram matrix updated to match. Only A's columns
    change, so only the Gram's rows and columns ``pos`` do: A_new^T a_new = A^T a_new, except at ``pos`` where it
    is a_new^T a_new (A itself is read, not copied)."""
    from objcam.solvers.regularization import _block_rows

    pos = np.asarray(pos, np.int64)
    cols = (tr.A[:, :, pos] + delta).astype(np.float32)
    G = np.array(tr.gram(), np.float64)
    step = _block_rows(tr.A.shape[2])  # float64 row blocks of A, as the Gram matrix itself is accumulated
    for c in range(tr.A.shape[0]):
        new = np.asarray(cols[c], np.float64)  # (M, B)
        upd = np.zeros((tr.A.shape[2], pos.size))  # (N, B): A_c^T a_new
        for r0 in range(0, tr.A.shape[1], step):
            upd += np.asarray(tr.A[c, r0 : r0 + step], np.float64).T @ new[r0 : r0 + step]
        upd[pos] = new.T @ new
        G[c][:, pos] = upd
        G[c][pos, :] = upd.T
    return Columns(pos, cols, G)


@contextmanager
def swapped(tr, cand: Columns, attrs: dict | None = None):
    """The Transport ``tr`` with the candidate's columns and Gram matrix, inside: ``tr.A``'s columns are replaced
    in place and put back on exit (so no A is copied; ``tr`` must not be used by another thread meanwhile).
    ``attrs``: added to the Transport's attributes, as the candidate's stored group will carry them (a point
    candidate's ``point_sources``, which the solve's basis and weak-texel rule read)."""
    import dataclasses

    old = tr.A[:, :, cand.pos].copy()
    tr.A[:, :, cand.pos] = cand.cols
    try:
        out = dataclasses.replace(tr, A=tr.A, attrs={**tr.attrs, **(attrs or {})})
        out._gram = cand.gram
        yield out
    finally:
        tr.A[:, :, cand.pos] = old


def point_sources(tr, direct, box: dict[str, dict], names: list[str]) -> dict[str, list]:
    """{target: the point sources (objcam.transport.points.PointSource) found in the bright blobs of its box
    pilot ``box[target]``} on the box Transport ``tr`` with the direct-light model ``direct``."""
    from objcam.solvers.sources import bright_blobs
    from objcam.transport.points import MAX_BLOBS, find_sources

    found = {}
    for name in names:
        p = box[name]
        x = np.asarray(p["envmap"], np.float64).reshape(-1, 3)[tr.texel_index]
        solved = np.asarray(p["mask"], bool).ravel()[tr.texel_index]
        lum = np.where(solved, x @ LUMA, 0.0)
        blobs = sorted(bright_blobs(lum, tr.grid, tr.texel_index), key=lambda b: -float(lum[b].sum()))[:MAX_BLOBS]
        found[name] = find_sources(direct, tr.grid, tr.texel_index, tr.A, p["y"], p["fitted"], x, blobs)
    return found


def point_transport(tr, direct, sources: list) -> tuple[Columns | None, list]:
    """(the box Transport ``tr`` with point-source columns at ``sources`` (objcam.transport.points) as
    :class:`Columns`, None when no source gave one; the sources used: one a texel)."""
    from objcam.transport.points import point_columns

    pos, delta, used = point_columns(direct, tr.grid, tr.texel_index, sources)
    return (replace_direct(tr, pos, delta) if pos.size else None), used


def pick(results: dict[str, dict[str, dict]], names: list[str], joint: bool) -> dict[str, str]:
    """{target: candidate}: box texels unless a candidate's fit beats theirs by more than the chi-squared's own
    spread (sqrt(2 / n) x the box's chi2 per value, n fitted values: the rule of objcam.solvers.sources and
    objcam.solvers.skyprofile; a fit better by less is not told from box texels by the photo), then the lowest
    chi2 among those that do, except that ``point`` excludes ``compact`` where both do (the module's docstring:
    the same question, and compact's better fit splits the source) (``results``: candidate -> target -> pilot
    result; "box" holds every target). joint: one candidate for all ``names``, by the chi2 summed over them,
    among the candidates solved for all."""
    if joint:
        full = [c for c, r in results.items() if all(n in r for n in names)]
        total = {c: sum(results[c][n]["chi2"] * results[c][n]["values"] for n in names) for c in full}
        n_all = sum(results["box"][n]["values"] for n in names)
        line = total["box"] * (1.0 - np.sqrt(2.0 / max(n_all, 1)))
        ok = _placed_over_mixed([c for c in full if c == "box" or total[c] < line])
        best = min(ok, key=lambda c: total[c])
        return {n: best for n in names}
    out = {}
    for n in names:
        box = results["box"][n]
        line = box["chi2"] * (1.0 - np.sqrt(2.0 / max(box["values"], 1)))
        ok = [c for c in results if n in results[c] and (c == "box" or results[c][n]["chi2"] < line)]
        out[n] = min(_placed_over_mixed(ok), key=lambda c: results[c][n]["chi2"])
    return out


def _placed_over_mixed(ok: list[str]) -> list[str]:
    """The candidates ``ok`` (those beating box texels, and box) without ``compact`` where ``point`` is among
    them."""
    return [c for c in ok if c != "compact"] if "point" in ok else ok


def for_camera(art, geo, targets: list, out: Path, sub: str, settings, valids, noise, model_choice: str | None,
               direct, mapping: dict[str, str], mode: str, capture: Path) -> dict:
    """The transport stage's ``auto`` / ``fit`` for one camera whose box A is built in ``out / sub`` with the
    direct-light model ``direct``: solve its targets on it, then on the candidates ``mode`` asks for: the narrow
    kernel's A (``sub`` + "k": the same settings, seeds and auto model choice ``model_choice``; ``fit``, or
    ``auto`` where the box solve left black sky) and the box A with narrow columns at the solves' compact bright
    blobs (``sub`` + "c"); give each target the candidate with the lowest chi2 (``mapping``: target -> group,
    updated) and delete the groups no target took. Returns the camera's metrics (``texel_kernel_auto``)."""
    import dataclasses
    import shutil

    from objcam.transport.build import build_camera
    from objcam.transport.engine import current
    from objcam.transport.storage import load_group, write_columns

    names = [t.name for t in targets]
    joint = not (art.description.albedo_object.known and art.description.albedo_support.known)
    if joint and mode == "auto":  # measured: a two-photo joint capture's transport 10 -> 58 s with the pilots
        return {"texel_kernel_auto": {"mode": mode, "skipped": "unknown albedo: the joint solve is not repeated "
                                      "per candidate (texel_kernel=fit does)"}}
    box_tr = load_group(out / sub)
    try:  # a capture the solve refuses (no usable pixel, say) is the solve stage's to report: keep box texels
        results = {"box": pilot(art, targets, box_tr, capture)}
    except Exception as e:  # noqa: BLE001
        return {"texel_kernel_auto": {"mode": mode, "skipped": f"{type(e).__name__}: {e}"[:300]}}
    box = results["box"]
    metrics: dict = {}
    want = names if mode == "fit" else triggered(box)
    if want:
        narrow = dataclasses.replace(settings, texel_kernel=NARROW,
                                     auto_choice=model_choice if settings.model == "auto" else None)
        mk = build_camera(geo, targets[0].camera, out / (sub + "k"), narrow, valids=valids, targets=names,
                          target_noise=noise)
        current().write_gram(out / (sub + "k"))
        asked = targets if joint else [t for t in targets if t.name in want]
        results["narrow"] = pilot(art, asked, load_group(out / (sub + "k")), capture)
        metrics["seconds_narrow"] = mk.get("seconds")
    grid_blobs = {n: np.flatnonzero(compact_blobs(box[n]["envmap"], box[n]["mask"]).ravel()) for n in names}
    texels = np.unique(np.concatenate(list(grid_blobs.values())))
    compact = None
    if texels.size and direct is not None:
        compact = compact_columns(box_tr, direct, texels)
        asked = targets if joint else [t for t in targets if grid_blobs[t.name].size]
        with swapped(box_tr, compact) as tr_c:
            results["compact"] = pilot(art, asked, tr_c, capture)
        metrics["compact_texels"] = int(compact.pos.size)
    points: dict[str, tuple] = {}  # group -> (Columns, targets, its attrs: the sources used)
    if direct is not None:
        found = point_sources(box_tr, direct, box, names)
        with_src = [t for t in targets if found[t.name]]
        # each target its own sources (another target's lamp is not this one's), one A for a joint solve
        parts = [(sub + "p", with_src)] if joint else [(f"{sub}p{i}", [t]) for i, t in enumerate(with_src)]
        for g, ts in parts if with_src else []:
            cand, used = point_transport(box_tr, direct, [s for t in ts for s in found[t.name]])
            if cand is not None:
                placed = {"point_sources": [s.record() for s in used]}  # the group's attrs, as stored
                points[g] = (cand, [t.name for t in ts], placed)
                with swapped(box_tr, cand, placed) as tr_p:
                    got = pilot(art, targets if joint else ts, tr_p, capture)
                results.setdefault("point", {}).update(got)
        if with_src:
            metrics["point_sources"] = {t.name: [s.record() for s in found[t.name]] for t in with_src}
    on_common_pixels(results, names)
    choice = pick(results, names, joint)  # a candidate only where results has it, so its A and columns are set
    groups = {"box": sub, "narrow": sub + "k", "compact": sub + "c"}
    if "compact" in choice.values():
        write_columns(out / sub, out / (sub + "c"), compact.pos, compact.cols, compact.gram)
    group = {n: groups.get(c) for n, c in choice.items()}
    for g, (cand, owners, placed) in points.items():
        took = [n for n in owners if choice[n] == "point"]
        if took:
            write_columns(out / sub, out / g, cand.pos, cand.cols, cand.gram, placed)
        group.update({n: g for n in took})
    mapping.update(group)
    for g in (sub, sub + "k"):
        if g not in mapping.values() and (out / g).exists():
            shutil.rmtree(out / g)
    rec = {n: {"dark_sky_area_box": round(box[n]["dark_sky_area"], 5), "kernel": choice[n],
               "values_compared": box[n]["values"]}
           | {f"chi2_{c}": round(r[n]["chi2"], 5) for c, r in results.items() if n in r}
           | {f"chi2_own_{c}": round(r[n]["chi2_own"], 5) for c, r in results.items() if "chi2_own" in r.get(n, {})}
           for n in names}
    return {"texel_kernel_auto": {"mode": mode, "targets": rec}} | metrics
