"""``make bench BENCH=gi``: the default A (``transport.model=auto``, interreflections included) against
path-traced columns WITH interreflections, rendered from a scene objcam did not write.

``--capture DIR --target NAME`` measures instead the A already built in an existing capture's ``objcam/transport``
(a hard-suite capture, whose files bench/hard/scene.py reads the same way: object.ply, targets/NAME.json, the
albedo), rendering the reference from that target's camera; no A is built and no direct-only row is written.

The core bench measures A only against direct light (max_depth 2) rendered through objcam's own scene builder;
this block measures what the default model is for: the image a texel lights, all bounces included.

- Capture: ``objcam synth`` (the bunny on a grey plane, albedo 0.6 / 0.5, one camera, 0.1% noise, the core
  bench's), run through objcam's default transport: model=auto, told the core bench's 0.1% target noise
  (``transport.auto_noise=0.001``; this capture's own target is rendered at low spp, and only its A is used), at
  which auto adds the interreflections (the block shows the transport's summary: what auto chose).
- Reference scene: bench/hard/scene.py (written from data_layout.md's text, never through objcam's scene
  builder, transport or envmap module) reading the capture's own files: object.ply, targets/t0.json, the albedo.
  Mitsuba's path tracer at ``max_depth`` (default 8: seven bounces), a box pixel filter, two seeds per column so
  the reference's own noise is subtracted (bench/run.py's column_error formula, restated here).
- The lit texel: a one-hot envmap written here (:func:`box_bitmap`); its emitted power and its direction are
  measured through Mitsuba for every column before it is used (a texel that Mitsuba does not emit as the box the
  contract means would make the comparison meaningless).
- Columns: texels chosen by a seeded uniform draw over the upper hemisphere's texels, without looking at A.

Column error = sqrt(sum_j max(||a_j - r_j||^2 - noise_j, 0) / sum_j ||r_j||^2) over the chosen columns, r_j the
mean of the two renders, noise_j = ||r_a - r_b||^2 / 4 (the variance of that mean); the same for the direct-only
model (``transport.model=direct``) to show what the interreflections are worth. Target (issue 28): <= 1.5%.

    python -m bench.gi_reference [--quick] [--write] [--columns 24] [--spp 1024] [--max-depth 8]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from bench.run import box_transport, group_note
from bench.sections import invocation, write_section

OUT = Path("bench/out/gi")
TITLE = "The default A against a path-traced reference with interreflections (issue 28)"
TARGET = 0.015
# auto decides from the target's noise whether the interreflections matter; at the core bench's 0.1% (stated
# here: this bench's own target is rendered at low spp, and only its A is used) it adds them by the gather
MODELS = (("auto (default), target noise 0.1%", ["transport.auto_noise=0.001"]),
          ("direct (the default without interreflections)", ["transport.model=direct"]))


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def box_bitmap(height: int, row: int, col: int, f: int = 8) -> np.ndarray:
    """(f H + 1, 2 f H, 3) float32: the contract's texel (row, col) of an H x 2H lat-long map lit at radiance 1,
    as a bitmap for bench/hard/scene.py (which hands Mitsuba the columns reversed): bench.hard.scene.contract_bitmap
    of the one-hot map.

    Mitsuba's envmap interpolates bilinearly between bitmap samples that sit at polar angle pi i / (rows - 1) and
    at the column centres. With f H + 1 rows, row i samples theta = pi i / (f H): the texel's boundary rows
    (i = f row, f (row + 1)) get 1/2 and the rows between them 1, so the interpolated radiance ramps from 0 to 1
    over 1/f of a texel row symmetrically about each boundary; columns f col .. f col + f - 1 get 1, so the ramp
    in azimuth is symmetric about the boundary too. The emitted power is the box texel's up to the ramps' second
    order (measured by :func:`emitted_power`)."""
    from bench.hard.scene import contract_bitmap

    env = np.zeros((height, 2 * height, 3), np.float32)
    env[row, col] = 1.0
    return contract_bitmap(env, f)


def texel_box(height: int, row: int, col: int) -> tuple[float, np.ndarray]:
    """(solid angle in sr, unit direction of the texel's centre) of the contract's texel (row, col): polar angle
    theta from +z over [pi row / H, pi (row + 1) / H], azimuth phi from +x towards +y over [pi col / H, ...]."""
    t0, t1 = math.pi * row / height, math.pi * (row + 1) / height
    p0, p1 = math.pi * col / height, math.pi * (col + 1) / height
    omega = (math.cos(t0) - math.cos(t1)) * (p1 - p0)
    t, p = 0.5 * (t0 + t1), 0.5 * (p0 + p1)
    return omega, np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


def emitted_power(bitmap: np.ndarray, height: int, row: int, col: int, k: int = 96) -> tuple[float, np.ndarray]:
    """(integral of the emitter's radiance in sr, its radiance-weighted mean direction, unit) for ``bitmap`` (the
    one-hot texel (row, col) of an H x 2H map) loaded the way bench/hard/scene.py loads it: Mitsuba's envmap
    evaluated on a midpoint grid of k x k directions per texel over the texel and its eight neighbours (the
    ramps reach 1/16 texel past its edges), weighted by sin(theta) dtheta dphi."""
    import drjit as dr
    import mitsuba as mi

    from bench.hard.scene import envmap_to_world

    em = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(bitmap[:, ::-1])),
                       "to_world": mi.ScalarTransform4f(envmap_to_world().tolist())})
    step = math.pi / height
    t_lo, t_hi = max(row - 1, 0) * step, min(row + 2, height) * step
    nt = k * round((t_hi - t_lo) / step)
    theta = t_lo + (np.arange(nt) + 0.5) * (t_hi - t_lo) / nt
    phi = (col - 1) * step + (np.arange(3 * k) + 0.5) * step / k
    T, P = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
    si.wi = mi.Vector3f(*(-d.T).astype(np.float32))  # eval looks up the direction -wi
    v = np.asarray(em.eval(si), np.float64)[0]  # (3, n): the grey bitmap's red channel
    w = v * np.sin(T).ravel() * ((t_hi - t_lo) / nt) * (step / k)
    m = (d * w[:, None]).sum(axis=0)
    return float(w.sum()), m / max(np.linalg.norm(m), 1e-30)


def choose_texels(height: int, n: int, seed: int, only_rows: list[int] | None = None) -> list[tuple[int, int]]:
    """n distinct texels (row, col) of the upper hemisphere (rows whose centre is above the horizon; ``only_rows``:
    those rows only, e.g. the two at the horizon), drawn uniformly with ``seed``: the rule never looks at A."""
    rows = [r for r in range(height) if math.pi * (r + 0.5) / height < math.pi / 2
            and (only_rows is None or r in only_rows)]
    cells = [(r, c) for r in rows for c in range(2 * height)]
    pick = np.random.default_rng(seed).choice(len(cells), size=min(n, len(cells)), replace=False)
    return [cells[i] for i in sorted(pick)]


def make_capture(root: Path, size: int, spp: int) -> Path:
    """The capture (cached): ``objcam synth`` of the bunny under forest, one size x size camera, 0.1% noise."""
    from objcam.synth.capture import SynthParams, synthesize

    cap = root / f"capture-{size}px"
    if not (cap / "capture.toml").is_file():
        shutil.rmtree(cap, ignore_errors=True)
        synthesize(cap, SynthParams(envmap="forest", spp=spp, cameras=[{"width": size, "height": size}],
                                    shot_noise=1e-3))
    return cap


def build_a(cap: Path, work: Path, sets: list[str]) -> tuple[object, dict]:
    """Run objcam's transport stage with ``sets``: (its box-texel Transport, provenance: seconds, whether the
    stage came from the cache, its summary, the group measured). The box-texel A (``cam0``, bench.run.box_transport)
    rather than t0's own: with texel_kernel=auto a target may keep point-source or narrow columns at its bright
    blobs, by design not the one-hot box texel the reference renders."""
    from objcam.pipeline.engine import Pipeline, parse_overrides

    pipe = Pipeline(cap, work, parse_overrides(sets), quiet=True)
    reports = pipe.run(until="transport")
    rep = {r.stage: r for r in reports}["transport"]
    rec = json.loads((work / "transport" / "stage.json").read_text())
    tr, group = box_transport(work / "transport", "t0")
    return tr, {"seconds": rec["wall_seconds"], "cached": rep.status == "cached", "summary": rec["summary"],
                "group": group}


def pooled(img: np.ndarray, f: int, pixel_index: np.ndarray) -> np.ndarray:
    """(M,) grey values of the f x f pooled pixels ``pixel_index`` (flat, pooled width) of img (h, w, 3)."""
    h, w = img.shape[0] // f, img.shape[1] // f
    p = img[: h * f, : w * f].reshape(h, f, w, f, -1).mean(axis=(1, 3)).mean(axis=-1)
    return p.reshape(-1)[pixel_index]


def reference(cap: Path, texels, height: int, spp: int, max_depth: int, f: int, pixel_index: np.ndarray,
              cache: Path, target: str = "t0") -> dict:
    """Two path-traced renders per texel (seeds 2 j + 1, 2 j + 2) through the camera of ``target``
    (targets/<target>.json), pooled to A's rows; cached in ``cache``."""
    import mitsuba as mi

    from bench.hard.scene import scene_dict

    if cache.is_file():
        z = dict(np.load(cache))
        if np.array_equal(z["pixel_index"], pixel_index) and z["texels"].tolist() == [list(t) for t in texels]:
            return z
    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb")
    import tomllib

    toml = tomllib.loads((cap / "capture.toml").read_text())
    camera = json.loads((cap / "targets" / f"{target}.json").read_text())
    albedo = (float(toml["albedo"]["object"]), float(toml["albedo"]["support"]))
    ref_a, ref_b, power, offset = [], [], [], []
    t0 = time.perf_counter()
    for j, (r, c) in enumerate(texels):
        bm = box_bitmap(height, r, c)
        p, d = emitted_power(bm, height, r, c)
        omega, centre = texel_box(height, r, c)
        power.append(p / omega - 1.0)
        offset.append(math.degrees(math.acos(float(np.clip(d @ centre, -1, 1)))))
        imgs = []
        for seed in (2 * j + 1, 2 * j + 2):
            scene = mi.load_dict(scene_dict(cap / "object.ply", camera, bm, *albedo, spp, seed, max_depth))
            imgs.append(pooled(np.asarray(mi.render(scene), np.float64)[..., :3], f, pixel_index))
        ref_a.append(imgs[0])
        ref_b.append(imgs[1])
        log(f"  column {j + 1}/{len(texels)} (row {r}, col {c}): power error {power[-1]:+.4f}, "
            f"direction {offset[-1]:.2f} deg off the centre")
    out = {"pixel_index": pixel_index, "texels": np.array(texels), "ref_a": np.array(ref_a), "ref_b": np.array(ref_b),
           "power_error": np.array(power), "direction_offset_deg": np.array(offset),
           "seconds": time.perf_counter() - t0, "spp": spp, "max_depth": max_depth}
    np.savez(cache, **out)
    return out


def column_errors(A: np.ndarray, cols: np.ndarray, ref: dict) -> tuple[float, list[float]]:
    """(pooled relative column error, per column) of A[:, cols] against the reference, the reference's own noise
    subtracted. A: (M, N) grey columns; cols: (n,) positions of the reference's texels in A's columns."""
    num = den = 0.0
    per = []
    for k, j in enumerate(cols):
        ra, rb = ref["ref_a"][k], ref["ref_b"][k]
        r = 0.5 * (ra + rb)
        a = A[:, j] if j >= 0 else np.zeros_like(r)
        noise = 0.25 * float(np.sum((ra - rb) ** 2))
        e = max(float(np.sum((a - r) ** 2)) - noise, 0.0)
        num += e
        den += float(np.sum(r**2))
        per.append(math.sqrt(e / max(float(np.sum(r**2)), 1e-300)))
    return math.sqrt(num / den), per


def part_errors(A: np.ndarray, cols: np.ndarray, ref: dict, on_object: np.ndarray) -> dict[str, float]:
    """{"object", "support"}: :func:`column_errors` over the pixels that see the object (``on_object`` (M,) bool)
    and over the others: the object's pixels (their faceted normals, 256 sub-pixel samples) and the support's have
    their own sampling, so their errors are told apart."""
    out = {}
    for name, rows in (("object", on_object), ("support", ~on_object)):
        sub = dict(ref, ref_a=ref["ref_a"][:, rows], ref_b=ref["ref_b"][:, rows])
        out[name] = column_errors(A[rows], cols, sub)[0] if rows.any() else float("nan")
    return out


def energy_ratios(A: np.ndarray, cols: np.ndarray, ref: dict) -> list[float]:
    """Per reference column, the light A's column puts in the image over the reference's: sum_i a_ij / sum_i r_ij
    (r the mean of the two renders; a texel A dropped counts 0). A: (M, N) grey columns; cols: (n,) as for
    :func:`column_errors`."""
    out = []
    for k, j in enumerate(cols):
        r = 0.5 * (ref["ref_a"][k] + ref["ref_b"][k])
        a = float(A[:, j].sum()) if j >= 0 else 0.0
        out.append(a / max(float(r.sum()), 1e-300))
    return out


def capture_a(cap: Path, target: str) -> tuple[object, dict]:
    """(the Transport already built for ``target`` in ``cap``/objcam/transport, its provenance as
    :func:`build_a` gives it): ``--capture``."""
    from objcam.transport import load_transport

    folder = cap / "objcam" / "transport"
    if not (folder / "stage.json").is_file():
        raise SystemExit(f"{folder}: no transport stage (run `objcam run {cap} --until transport` first)")
    rec = json.loads((folder / "stage.json").read_text())
    return load_transport(folder, target), {"seconds": rec["wall_seconds"], "cached": True,
                                            "summary": rec.get("summary", "")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a 48 x 48 camera, 6 columns at 144 spp (a smoke run)")
    ap.add_argument("--size", type=int, default=None, help="camera pixels (default 128, the core bench's)")
    ap.add_argument("--columns", type=int, default=None, help="reference columns (default 24)")
    ap.add_argument("--spp", type=int, default=None, help="samples per pixel of each reference render (1024)")
    ap.add_argument("--max-depth", type=int, default=8, help="reference path depth (> 2: interreflections)")
    ap.add_argument("--seed", type=int, default=28, help="seed of the columns' draw")
    ap.add_argument("--rows", default=None, help="draw the columns from these envmap rows only (comma-separated, "
                    "e.g. 14,15: the two above the horizon at 32 x 64)")
    ap.add_argument("--capture", type=Path, default=None, help="measure the A already built in this capture's "
                    "objcam/transport (e.g. a hard-suite capture) instead of the core bench's synth capture")
    ap.add_argument("--target", default=None, help="with --capture: the target whose camera and A are measured "
                    "(default: the capture's first)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--write", action="store_true", help="write the block of bench/results.md")
    a = ap.parse_args(argv)
    if a.max_depth <= 2:
        ap.error("--max-depth must be > 2 (2 is direct light only)")
    os.environ.setdefault("OBJCAM_QUIET", "1")
    size = a.size or (48 if a.quick else 128)
    n_cols = a.columns or (6 if a.quick else 24)
    spp = a.spp or (144 if a.quick else 1024)  # squares: the multijitter sampler's
    a.out.mkdir(parents=True, exist_ok=True)
    if a.capture is not None:
        import tomllib

        cap = a.capture
        target = a.target or tomllib.loads((cap / "capture.toml").read_text())["targets"][0]["name"]
        models = [(f"the capture's A ({cap.name}, {target})", None)]
        tag = f"{cap.name}-{target}"
    else:
        cap, target, models, tag = make_capture(a.out, size, 64), "t0", MODELS, f"{size}px"
    rows, ref = [], None
    for label, sets in models:
        t = time.perf_counter()
        if sets is None:
            tr, prov = capture_a(cap, target)
        else:
            tr, prov = build_a(cap, a.out / f"work-{size}px-{label.split()[0]}", sets)
        log(f"{label}: A {'from the cache' if prov['cached'] else f'built in {time.perf_counter() - t:.0f} s'}")
        if tr.env_height != 32 and ref is None:
            log(f"  envmap height {tr.env_height}")
        if ref is None:
            texels = choose_texels(tr.env_height, n_cols, a.seed,
                                   [int(r) for r in a.rows.split(",")] if a.rows else None)
            cache = a.out / (f"reference-{tag}-{n_cols}cols-{spp}spp-d{a.max_depth}-s{a.seed}"
                             + (f"-rows{a.rows.replace(',', '_')}" if a.rows else "") + ".npz")
            log(f"reference: {len(texels)} columns x 2 renders at {spp} spp, max_depth {a.max_depth}")
            ref = reference(cap, texels, tr.env_height, spp, a.max_depth, tr.downsample, tr.pixel_index, cache,
                            target)
        flat = [r * 2 * tr.env_height + c for r, c in ref["texels"].tolist()]
        pos = {int(t): i for i, t in enumerate(tr.texel_index)}
        cols = np.array([pos.get(t, -1) for t in flat])  # a texel A dropped (below the horizon): a zero column
        A = np.asarray(tr.A.mean(axis=0) if tr.A.shape[0] > 1 else tr.A[0], np.float64)
        err, per = column_errors(A, cols, ref)
        parts = part_errors(A, cols, ref, np.asarray(tr.object_fraction) > 0)
        energy = energy_ratios(A, cols, ref)
        rows.append({"model": label, "sets": sets, "column_error": err, "per_column": per, "energy_ratio": energy,
                     "column_error_object": parts["object"], "column_error_support": parts["support"], **prov})
        log(f"  column error {100 * err:.2f}%; energy A / reference per column: "
            + " ".join(f"{e:.3f}" for e in energy))
    res = {"size": tr.camera.width if a.capture else size, "columns": n_cols, "spp": spp, "max_depth": a.max_depth,
           "seed": a.seed, **({"capture": str(cap), "target": target} if a.capture else {}),
           "texels": ref["texels"].tolist(), "power_error": ref["power_error"].tolist(),
           "direction_offset_deg": ref["direction_offset_deg"].tolist(), "reference_seconds": float(ref["seconds"]),
           "load": os.getloadavg()[0], "rows": rows}
    raw = a.out / f"gi-{tag}-{n_cols}cols-{spp}spp-d{a.max_depth}-s{a.seed}.json"
    if a.capture is not None:  # the raw rows beside the reference's cache
        res["raw"] = str(raw)
        raw.write_text(json.dumps(res, indent=1))
    md = markdown(res, argv)
    print(md)
    if a.write and a.capture is not None:
        log("--write writes the core bench's block: not with --capture (its rows are the gi-*.json in --out)")
    elif a.write:
        Path("bench/gi_rows.json").write_text(json.dumps(res, indent=1) + "\n")
        write_section("gi", md, TITLE)
    return 0


def markdown(res: dict, argv) -> str:
    L = [f"{invocation('bench.gi_reference', argv)}; load {res['load']:.1f}. Camera {res['size']} x {res['size']}, "
         f"{res['columns']} columns (texels drawn uniformly over the upper hemisphere, seed {res['seed']}), "
         f"2 x {res['spp']} spp per column at max_depth {res['max_depth']} ({res['reference_seconds']:.0f} s). "
         f"The one-hot texels as Mitsuba emits them: power within "
         f"{100 * max(abs(p) for p in res['power_error']):.2f}% of the box's solid angle, centre within "
         f"{max(res['direction_offset_deg']):.2f} deg. Raw rows: {res.get('raw', 'bench/gi_rows.json')}.", "",
         "| A | column error (GI reference) | target <= 1.5% | object / support pixels | A time (s) | "
         "median / max column error | energy A / reference: median (min-max) | transport |",
         "|---|---:|---|---:|---:|---:|---:|---|"]
    for r in res["rows"]:
        met = "met" if r["column_error"] <= TARGET else "missed" if r["model"].startswith("auto") else ""
        when = f"{r['seconds']:.1f}" + (" (cached: an earlier run's)" if r["cached"] else "")
        e = r["energy_ratio"]
        err = f"{100 * r['column_error']:.2f}%{group_note(r.get('group', 'cam0'))}"
        split = (f"{100 * r['column_error_object']:.2f}% / {100 * r['column_error_support']:.2f}%"
                 if "column_error_object" in r else "-")
        L.append(f"| {r['model']} | {err} | {met} | {split} | {when} | "
                 f"{100 * float(np.median(r['per_column'])):.2f}% / {100 * max(r['per_column']):.2f}% | "
                 f"{float(np.median(e)):.3f} ({min(e):.3f}-{max(e):.3f}) | {r['summary'][:120]} |")
    return "\n".join(L)


if __name__ == "__main__":
    sys.exit(main())
