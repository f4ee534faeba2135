"""``make bench BENCH=resolution``: does a finer envmap recover more of the light, and where does it stop (issue 26)?

    python -m bench.resolution_bench [--write] [--out bench/out/resolution] [--hdris forest,courtyard,city,sunrise]
                                     [--noise 0.001,0.02] [--heights 32,64,128] [--spp 4096]
                                     [--paper-heights 32,64] [--reuse]

The core bench's scene (bench/run.py: the bunny on a grey plane, one 128 x 128 camera, grey known albedo), its
targets rendered by Mitsuba (objcam.synth's split estimator: stratified direct light plus path-traced indirect
light, never through objcam's A) from the clean renders with the camera's noise applied at each level. For each
height objcam runs with its defaults up to ``evaluate`` (``transport.env_height`` = the height) with the default
solve (the edge prior, exact) and the method's damped solver (``solve.method=paper``, quadratic prior, as the core
bench runs it); heights objcam.transport.budget refuses (memory, or planned time past ``--max-seconds``) get a row
saying why. Each envmap is scored against the truth at its own height (evaluate's metrics and baselines) and
area-averaged to 32 x 64 against the truth at 32 x 64 on the 32 x 64 solve's mask (the issue's comparison), beside
the constant and row-mean maps (objcam.baselines). Then ``transport.env_height=auto`` runs (up to ``transport``)
on each noise level; each HDRI's choice is read from its record (objcam.transport.resolution, per target) and
scored by the fixed-height run at that height.

``--write`` puts the block into bench/results.md and the raw rows into bench/resolution_rows.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from bench.sections import invocation, write_section

TITLE = "Resolution: finer envmaps and transport.env_height=auto (issue 26)"
HDRIS = ("forest", "courtyard", "city", "sunrise")
METHODS = (("default (edges, exact)", {}), ("paper (damped)", {"method": "paper", "prior": "smooth"}))
KEYS = ("ssim", "tonemapped_rmse", "relative_rmse", "brightest_angle_deg")
READ_NOISE = 100.0  # electrons (objcam.synth's default)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def camera_exposure(clean: np.ndarray, noise: float, read_noise: float = READ_NOISE) -> float:
    """Electrons per unit radiance giving the median positive pixel a relative camera noise of ``noise`` with the
    read noise counted (objcam.synth.noise.auto_exposure counts shot noise only: at 2% its exposure of 2,500
    electrons with 100 of read noise gives 4.5%): e = (1 + sqrt(1 + 4 n^2 r^2)) / (2 n^2) electrons."""
    pos = clean[np.isfinite(clean) & (clean > 0)]
    med = float(np.median(pos)) if pos.size else 1.0
    e = (1.0 + np.sqrt(1.0 + 4.0 * noise**2 * read_noise**2)) / (2.0 * noise**2)
    return float(e / med)


def noisy_capture(out: Path, renders: Path, hdris, noise: float, seed: int = 0) -> Path:
    """A capture of every HDRI's target at camera noise ``noise`` (relative, shot and read noise, at the median
    pixel; the synth's camera model) applied to the cached clean render; noise_sigma = hypot(camera, render
    noise)."""
    from objcam.image_io import read_exr, write_exr
    from objcam.synth.noise import apply_noise, relative_noise

    cap = out / f"capture-{noise:g}"
    key = json.dumps({"hdris": list(hdris), "noise": noise, "seed": seed, "renders": str(renders), "read": True})
    if (cap / "bench_params.json").is_file() and (cap / "bench_params.json").read_text() == key:
        return cap
    shutil.rmtree(cap, ignore_errors=True)
    (cap / "targets").mkdir(parents=True)
    (cap / "truth").mkdir()
    shutil.copy(renders / "object.ply", cap / "object.ply")
    toml, truth = [], {}
    metas = json.loads((renders / "truth" / "truth.json").read_text())["targets"]
    for i, h in enumerate(hdris):
        meta = metas[h]
        clean = read_exr(renders / meta["clean_image"])
        exposure = camera_exposure(clean, noise)
        img, _ = apply_noise(clean, exposure, READ_NOISE, meta.get("white_level"),
                             np.random.default_rng(seed + 1000 * i), True)
        med = float(np.median(clean[clean > 0]))
        sigma = float(np.hypot(relative_noise(med, exposure, READ_NOISE), meta["render_noise_sigma"]))
        write_exr(cap / "targets" / f"{h}.exr", img)
        shutil.copy(renders / "targets" / f"{h}.json", cap / "targets" / f"{h}.json")
        shutil.copy(renders / "truth" / f"{h}.exr", cap / "truth" / f"{h}.exr")
        truth[h] = f"truth/{h}.exr"
        toml.append(f'[[targets]]\nname = "{h}"\nimage = "targets/{h}.exr"\ncamera = "targets/{h}.json"\n'
                    f'noise_sigma = {sigma:.6g}\n')
    (cap / "capture.toml").write_text('[scene]\nobject = "object.ply"\n\n[albedo]\nobject = 0.6\nsupport = 0.5\n\n'
                                      + "\n".join(toml))
    (cap / "truth" / "truth.json").write_text(json.dumps({"envmaps": truth}, indent=2))
    (cap / "bench_params.json").write_text(key)
    return cap


def clean_renders(out: Path, hdris, spp: int) -> Path:
    """One folder with every HDRI's clean render, camera, truth and render noise, rendered once by objcam.synth
    (split estimator at ``spp``; cached in OUT/synth by bench.run.synth_targets' naming)."""
    from objcam.synth.capture import SynthParams, synthesize

    dest = out / f"renders-{spp}"
    index = dest / "truth" / "truth.json"
    have = json.loads(index.read_text())["targets"] if index.is_file() else {}
    if all(h in have and (dest / have[h]["clean_image"]).is_file() for h in hdris):
        return dest  # every HDRI's clean render is here (its synth folder may be gone)
    (dest / "targets").mkdir(parents=True, exist_ok=True)
    (dest / "truth").mkdir(exist_ok=True)
    metas = {}
    for h in hdris:
        src = out / "synth" / f"{h}-split-{spp}spp-128px-std"
        if not (src / "capture.toml").is_file():
            shutil.rmtree(src, ignore_errors=True)
            t0 = time.perf_counter()
            synthesize(src, SynthParams(envmap=h, spp=spp, cameras=[{"width": 128, "height": 128}],
                                        estimator="split", shot_noise=1e-3, noise=True))
            log(f"  rendered '{h}' ({spp} spp, split) in {time.perf_counter() - t0:.0f} s")
        meta = json.loads((src / "truth" / "truth.json").read_text())["targets"]["t0"]
        shutil.copy(src / meta["clean_image"], dest / "truth" / f"{h}-clean.exr")
        shutil.copy(src / "targets" / "t0.json", dest / "targets" / f"{h}.json")
        shutil.copy(src / "truth" / "envmap.exr", dest / "truth" / f"{h}.exr")
        shutil.copy(src / "object.ply", dest / "object.ply")
        metas[h] = meta | {"clean_image": f"truth/{h}-clean.exr"}
    (dest / "truth" / "truth.json").write_text(json.dumps({"targets": metas}, indent=2))
    return dest


def refusal(height: int, max_seconds: float) -> str | None:
    """Why objcam.transport.budget refuses a one-HDRI capture's transport at ``height`` (None: it fits): 16,384
    pooled pixels, a support plane, grey albedo, one target (the question is asked per HDRI; this bench solves
    its four HDRIs on one A, which the transport stage would plan at four targets' solves)."""
    from objcam.transport import budget
    from objcam.transport.resolution import affordable

    _, refused = affordable([height], lambda h: [budget.estimate(128 * 128, budget.kept_texels(h, True), 1)],
                            max_seconds)
    return refused.get(height)


def score32(est: np.ndarray, truth_full: np.ndarray, mask32: np.ndarray) -> dict:
    """The estimate area-averaged to 32 x 64 against the truth there, on the 32 x 64 solve's mask, with the
    constant and row-mean baselines."""
    from objcam.baselines import with_baselines
    from objcam.envmap import resample_to_height
    from objcam.metrics import envmap_metrics

    e32, t32 = resample_to_height(est, 32), resample_to_height(truth_full, 32)
    m = with_baselines(envmap_metrics(e32, t32, mask32), t32, mask32)
    return {k: m[k] for k in KEYS} | {"baselines": {b: {k: v[k] for k in KEYS} for b, v in m["baselines"].items()}}


def run_height(cap: Path, work: Path, height: int, hdris, mask32: dict | None, methods=METHODS) -> list[dict]:
    """objcam at one height with each solve method; one row per (method, HDRI)."""
    from objcam.envmap import read_latlong, read_latlong_mask
    from objcam.pipeline.engine import Pipeline

    rows = []
    for method, sparams in methods:
        pipe = Pipeline(cap, work, overrides={"transport": {"env_height": height}, "solve": sparams}, quiet=True)
        t0 = time.perf_counter()
        pipe.run(until="evaluate")
        log(f"    {method}: {time.perf_counter() - t0:.0f} s wall")
        trec = json.loads((work / "transport" / "stage.json").read_text())
        srec = json.loads((work / "solve" / "stage.json").read_text())
        ev = json.loads((work / "evaluate" / "metrics.json").read_text())
        for h in hdris:
            sj = json.loads((work / "solve" / h / "solve.json").read_text())
            est = read_latlong(work / "solve" / h / "envmap.exr")[..., :3].astype(np.float64)
            truth = read_latlong(cap / "truth" / f"{h}.exr")[..., :3].astype(np.float64)
            own_mask = read_latlong_mask(work / "solve" / h / "envmap_mask.png")
            m32 = mask32[h] if mask32 is not None else own_mask
            rows.append({
                "height": height, "method": method, "hdri": h,
                "at_height": {k: ev[h].get(k) for k in KEYS}
                | {"baselines": {b: {k: v.get(k) for k in KEYS} for b, v in ev[h]["baselines"].items()}},
                "at_32": score32(est, truth, m32),
                "a_seconds": trec["wall_seconds"], "a_cpu_seconds": trec["metrics"].get("cpu_seconds"),
                "a_peak_rss_mb": trec.get("peak_rss_mb"), "texels": trec["metrics"].get("texels_kept"),
                "a_load": trec.get("load_average"),
                "solve_seconds": sj.get("solve_seconds"), "solve_cpu_seconds": sj.get("solve_cpu_seconds"),
                "solve_stage_seconds": srec["wall_seconds"], "solve_peak_rss_mb": srec.get("peak_rss_mb"),
                "solve_load": srec.get("load_average"), "kkt": sj.get("kkt_residual_max"),
                "unknowns": (sj.get("basis") or {}).get("unknowns"),
            })
    return rows


def auto_from_fixed(cap: Path, works: dict[int, Path], hdris) -> dict:
    """The rule of ``transport.env_height=auto`` (objcam.transport.resolution.choose_height's per-target part:
    target_fit and walk, with the stage's noise) run on the fixed-height runs' transports, which are the A's the
    stage would build (same settings and seed); a target's finer heights are not fitted once its walk has stopped
    (the stage's rule does not build them either). Returns a record shaped like the stage's."""
    from objcam.schemas.artifacts import SceneArtifact
    from objcam.transport import load_transport
    from objcam.transport.resolution import Z, blind_transport, pooled_target, target_fit, walk

    t0, c0 = time.perf_counter(), time.process_time()
    art = SceneArtifact.load(next(iter(works.values())) / "scene")
    targets = {t.name: t for t in art.targets}
    out = {}
    for h in hdris:
        t = targets[h]
        fits, blind, sigma_abs, rel, coarser = {}, {}, None, None, None
        for height, work in sorted(works.items()):
            tr = load_transport(work / "transport", h)
            img, ok, rel, sigma_abs = pooled_target(t, art.folder, tr)
            fits[height] = target_fit(tr, img, ok, rel)
            if coarser is not None:  # the step's baseline: this grid blind inside the coarser texels
                blind[height] = target_fit(blind_transport(coarser, tr), img, ok, rel)
            coarser = tr
            if walk(fits, sigma_abs, blind=blind)[0] < height:  # the walk stopped below: finer fits cannot change
                break
        del coarser, tr
        chosen, steps = walk(fits, sigma_abs, blind=blind)
        out[h] = {"height": chosen, "noise_rel": rel, "steps": steps}
    return {"record": {"height": max(v["height"] for v in out.values()), "targets": out, "z": Z, "refused": {},
                       "from": "fixed-height transports"},
            "wall_seconds": round(time.perf_counter() - t0, 1), "cpu_seconds": round(time.process_time() - c0, 1),
            "peak_rss_mb": None, "load": os.getloadavg()[0]}


def run_auto(cap: Path, work: Path) -> dict:
    """``transport.env_height=auto`` up to the transport: its record (objcam.transport.resolution)."""
    from objcam.pipeline.engine import Pipeline

    t0 = time.perf_counter()
    Pipeline(cap, work, overrides={"transport": {"env_height": "auto"}}, quiet=True).run(until="transport")
    trec = json.loads((work / "transport" / "stage.json").read_text())
    rec = trec["metrics"]["env_height_auto"]
    return {"record": rec, "wall_seconds": round(time.perf_counter() - t0, 1),
            "cpu_seconds": rec.get("cpu_seconds"), "peak_rss_mb": trec.get("peak_rss_mb"),
            "load": trec.get("load_average")}


def f(v, fmt=".3f") -> str:
    return "-" if v is None else format(v, fmt)


def markdown(rows: list[dict], refused: dict, autos: dict, args, hdris, noises) -> str:
    lines = [invocation("bench.resolution_bench", args.argv), "",
             f"Scene: the core bench's (bunny on a grey plane, 128 x 128 camera, grey known albedo); targets rendered "
             f"by Mitsuba (split estimator, {args.spp} spp) with camera noise applied at each level (noise_sigma "
             f"states camera and render noise together). Machine: {os.cpu_count()} cores shared with other agents "
             "(`load`: 1-minute load average at the stage's start): wall times are inflated; CPU beside them.", "",
             "SSIM / tonemapped RMSE / relative RMSE / brightest-source angle (deg): at the solve's own height "
             "against the truth there, and area-averaged to 32 x 64 against the truth at 32 x 64 on the 32 x 64 "
             "solve's mask. Baselines (constant / row-mean map, objcam.baselines) at 32 x 64.", ""]
    for noise in noises:
        lines += [f"**camera noise {noise:g}**", "",
                  "| HDRI | height | method | SSIM own | SSIM @32 | tm RMSE @32 | rel RMSE @32 | bright deg @32 | "
                  "SSIM const / row-mean @32 | tm RMSE const / row-mean @32 | A s (CPU) | solve s (CPU) | "
                  "peak RSS MB (A / solve) | load |",
                  "|---|---|---|---:|---:|---:|---:|---:|---|---|---|---|---|---|"]
        for h in hdris:
            for r in [r for r in rows if r["noise"] == noise and r["hdri"] == h]:
                a, o, b = r["at_32"], r["at_height"], r["at_32"]["baselines"]
                lines.append(
                    f"| {h} | {r['height']} | {r['method']} | {f(o['ssim'])} | {f(a['ssim'])} | "
                    f"{f(a['tonemapped_rmse'])} | {f(a['relative_rmse'], '.2f')} | "
                    f"{f(a['brightest_angle_deg'], '.1f')} | {f(b['constant']['ssim'])} / {f(b['row_mean']['ssim'])} | "
                    f"{f(b['constant']['tonemapped_rmse'])} / {f(b['row_mean']['tonemapped_rmse'])} | "
                    f"{f(r['a_seconds'], '.0f')} ({f(r['a_cpu_seconds'], '.0f')}) | "
                    f"{f(r['solve_seconds'], '.1f')} ({f(r['solve_cpu_seconds'], '.1f')}) | "
                    f"{f(r['a_peak_rss_mb'], '.0f')} / {f(r['solve_peak_rss_mb'], '.0f')} | "
                    f"{f(r['solve_load'], '.1f')} |")
            for height, why in refused.items():
                lines.append(f"| {h} | {height} | refused | {why} |||||||||||")
        lines.append("")
    lines += ["**transport.env_height=auto** (default solve; auto's SSIM @32 against the best fixed height's):", "",
              "| noise | HDRI | auto's height | its test (gain vs threshold, in noise variances) | SSIM @32 auto | "
              "best fixed (height) | within 0.02 |", "|---|---|---|---|---:|---|---|"]
    for noise in noises:
        au = autos.get(noise)
        if au is None:
            continue
        for h in hdris:
            t = au["record"]["targets"][h]
            fixed = {r["height"]: r["at_32"]["ssim"] for r in rows
                     if r["noise"] == noise and r["hdri"] == h and r["method"] == METHODS[0][0]}
            best = max(fixed, key=fixed.get)
            mine = fixed.get(t["height"])
            steps = "; ".join(f"{s['from']}->{s['to']}: {s['gain']:,.0f} {'>' if s['supported'] else '<='} "
                              f"{s['threshold']:,.0f}" for s in t["steps"])
            ok = mine is not None and fixed[best] - mine <= 0.02
            lines.append(f"| {noise:g} | {h} | {t['height']} | {steps} | {f(mine)} | {f(fixed[best])} ({best}) | "
                         f"{'yes' if ok else 'no'} |")
        how = ("the rule on the fixed-height runs' A" if au["record"].get("from") else "transport with auto")
        refused_txt = "; ".join(f"{k}: {v}" for k, v in au["record"]["refused"].items()) or "as above"
        lines.append(f"| {noise:g} | (capture) | {au['record']['height']} | {how}: {au['wall_seconds']:.0f} s wall, "
                     f"{f(au['cpu_seconds'], '.0f')} s CPU, peak {f(au['peak_rss_mb'], '.0f')} MB, load "
                     f"{f(au['load'], '.1f')}; refused: {refused_txt} ||||")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("bench/out/resolution"))
    ap.add_argument("--results", type=Path, default=Path("bench/results.md"))
    ap.add_argument("--hdris", default=",".join(HDRIS))
    ap.add_argument("--noise", default="0.001,0.02")
    ap.add_argument("--heights", default="32,64,128")
    ap.add_argument("--spp", type=int, default=4096)
    ap.add_argument("--max-seconds", type=float, default=600.0, help="refuse heights planned past this (budget)")
    ap.add_argument("--auto", choices=("fixed", "stage", "none"), default="fixed",
                    help="env_height=auto's choice: 'fixed' runs its rule on the fixed-height runs' A (the same A "
                         "the stage builds), 'stage' runs the transport stage with env_height=auto (A built again)")
    ap.add_argument("--paper-heights", default=None, help="heights the damped solver also runs at (default: all)")
    ap.add_argument("--reuse", action="store_true", help="take a noise level's rows from OUT/rows-NOISE.json when "
                    "there (two levels run as two processes, then merged)")
    args = ap.parse_args(argv)
    args.argv = argv
    os.environ.setdefault("OBJCAM_QUIET", "1")
    hdris = [h for h in args.hdris.split(",") if h]
    noises = [float(v) for v in args.noise.split(",") if v]
    heights = sorted(int(v) for v in args.heights.split(",") if v)
    paper_at = heights if args.paper_heights is None else [int(v) for v in args.paper_heights.split(",") if v]
    args.out.mkdir(parents=True, exist_ok=True)
    renders = None if args.reuse and all((args.out / f"rows-{n:g}.json").is_file() for n in noises) else \
        clean_renders(args.out, hdris, args.spp)
    refused = {h: why for h in heights if (why := refusal(h, args.max_seconds))}
    rows, autos = [], {}
    from objcam.envmap import read_latlong_mask

    for noise in noises:
        saved = args.out / f"rows-{noise:g}.json"
        if args.reuse and saved.is_file():  # measured by an earlier (or a parallel) run: merged, not rerun
            d = json.loads(saved.read_text())
            rows += d["rows"]
            if d.get("auto"):
                autos[noise] = d["auto"]
            continue
        cap = noisy_capture(args.out, renders, hdris, noise)
        mask32 = None
        for height in [h for h in heights if h not in refused]:
            log(f"  noise {noise:g}, {height} x {2 * height}")
            work = args.out / "work" / f"n{noise:g}-h{height}"
            methods = METHODS if height in paper_at else METHODS[:1]
            for r in run_height(cap, work, height, hdris, mask32, methods):
                rows.append(r | {"noise": noise})
            if mask32 is None:
                mask32 = {h: read_latlong_mask(work / "solve" / h / "envmap_mask.png") for h in hdris}
            # written after every height: a run stopped later still leaves its finished heights for --reuse
            (args.out / f"rows-{noise:g}.json").write_text(json.dumps(
                {"rows": [r for r in rows if r["noise"] == noise], "auto": None, "partial": True},
                indent=1, default=float))
        if args.auto == "stage":
            log(f"  noise {noise:g}: env_height=auto")
            autos[noise] = run_auto(cap, args.out / "work" / f"n{noise:g}-auto")
        elif args.auto == "fixed":
            works = {h: args.out / "work" / f"n{noise:g}-h{h}" for h in heights if h not in refused}
            autos[noise] = auto_from_fixed(cap, works, hdris)
        mine = [r for r in rows if r["noise"] == noise]
        (args.out / f"rows-{noise:g}.json").write_text(json.dumps({"rows": mine, "auto": autos.get(noise)},
                                                                  indent=1, default=float))
    report = markdown(rows, refused, autos, args, hdris, noises)
    print(report)
    if args.write:
        write_section("resolution", report, TITLE, args.results)
        tmp = args.results.parent / "resolution_rows.json.tmp"  # beside results.md
        tmp.write_text(json.dumps({"rows": rows, "refused": {str(k): v for k, v in refused.items()},
                                   "auto": {str(k): v for k, v in autos.items()}}, indent=1, default=float))
        tmp.replace(args.results.parent / "resolution_rows.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
