"""End-to-end benchmark of issues 3 and 4: ``objcam run`` from raw photos against the same scene given known
geometry and cameras.

    .venv/bin/python -m bench.e2e_bench [--out bench/out/e2e] [--downsample 4] [--set STAGE.PARAM=VALUE ...]
                                        [--albedo known unknown] [--with-probe] [--hdr-only] [--no-hdr]
                                        [--no-known] [--views 24 --width 800 --height 600]

1. HDR merge (seconds): 5-frame raw brackets of the bundled sunny HDRIs (city, sunrise) merged back, noise-free and
   with the synthetic sensor's noise (the numbers tests/test_ingest_hdr.py asserts).
2. A synthetic photographed capture (``objcam synth --full``: 24 DNG views at 800 x 600 of the bunny on the printed
   board, the target as a 5-frame bracket, a chrome ball, object.ply in its own frame and millimetres), rendered
   once and cached under ``--out`` by its parameters (``full_<hash>/capture``; ~25 min on 2 busy cores).
3. Per albedo variant (``--albedo``): the capture as ``synth --full`` writes it with ``albedo_known`` on or off
   (``capture_<variant>``: the same raws, hard-linked, capture.toml rewritten; the chrome ball is left out unless
   ``--with-probe``: evaluate compares with truth/ either way, and the probe stage is issue 5's), and
   ``objcam run`` on it from the raws (``work_raws_<variant>``): ingest -> sfm -> geometry -> texture -> scene ->
   transport -> solve -> evaluate -> analysis -> report.
4. Its known-geometry twin (``known_<variant>``, run into ``work_known_<variant>``): the true object mesh in world
   metres (truth/object_world.ply), the true target camera (truth/cameras/targets), the same target pixels (ingest's
   merged bracket and its valid mask as the target's mask, so both runs fit the same photo) and the same
   ``[albedo]`` declaration; truth/ copied for evaluate.
5. Compares evaluate's metrics.json (SSIM, tonemapped RMSE, relative RMSE, brightest-source angle): target within
   10% of the known-geometry run (angles: or within half a 32-row texel); the cameras against truth (centre mm,
   rotation deg: target 0.5 mm / 0.05 deg), registered/total, ingest + sfm time (target < 2 min) and every stage's
   time with the load it started under; the target's (and ball's) merged bracket against its noise-free render.

Both runs of a variant use the same stage parameters: ``--set`` applies to both; ``--downsample`` sets
transport.downsample (the 800 x 600 target would otherwise be a 480,000-row A); with known albedo also
``evaluate.scale_invariant=true``: photographed images are in decoded value per second = sensor gain x radiance,
a gain objcam does not know, so the envmap is right only up to that one factor (unknown albedo: evaluate already
fits a scale per channel). Reruns are cheap: the capture is cached and ``objcam run`` skips stages whose inputs
and code did not change. Writes ``results.json`` and ``results.md`` beside the capture and prints the markdown;
exit status 0 when every variant is within 10%.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# views at 64 spp: at synth's default 16 the renders' Monte Carlo noise (several % per pixel, far above a DSLR's at
# base ISO) put the ChArUco corners at 0.34 px RMS and the worst view 0.57 mm / 0.051 deg from truth; at 64 spp
# 0.39 mm / 0.032 deg
E2E_FULL = dict(n_views=24, width=800, height=600, view_spp=64)
STAGES = ("ingest", "sfm", "geometry", "texture", "probe", "scene", "transport", "solve", "evaluate", "analysis",
          "report")
METRICS = (("ssim", "SSIM", +1), ("tonemapped_rmse", "tonemapped RMSE", -1), ("relative_rmse", "relative RMSE", -1),
           ("brightest_angle_deg", "brightest angle (deg)", -1))
#: brightest-source angles are compared in absolute terms too: half a texel of the 32-row solve grid
ANGLE_SLACK_DEG = 180.0 / 32 / 2
WB = (2.0, 1.0, 1.5)


def loadavg() -> str:
    return " / ".join(Path("/proc/loadavg").read_text().split()[:3])


# ------------------------------------------------------------------------------------------------ HDR merge


def hdri_merge(name: str, stop: float, noisy: bool, frames: int = 5, seed: int = 1) -> dict:
    """A ``frames``-frame DNG bracket (``stop`` EV apart, the longest putting the median texel at a quarter of white)
    of the bundled HDRI ``name`` merged back; errors per texel relative to its brightest channel."""
    import tempfile

    from objcam.capture.dng import NoiseModel, synth_bracket
    from objcam.capture.hdr import merge_raw_bracket
    from objcam.envmap import area_downsample
    from objcam.synth.assets import load_bundled_envmap

    env = load_bundled_envmap(name).astype(np.float64)
    lum = env.max(axis=2)
    t_long = 0.25 / float(np.median(lum))
    times = [t_long * 2.0 ** (-stop * k) for k in range(frames)]
    noise = NoiseModel(full_well_e=20000.0, read_noise_e=3.0, seed=seed) if noisy else None
    with tempfile.TemporaryDirectory(prefix="objcam-hdr-bench-") as tmp:
        per_s = (env / np.array(WB)).repeat(2, 0).repeat(2, 1)
        paths = synth_bracket(Path(tmp), per_s, times, noise=noise, wb=WB)
        res = merge_raw_bracket(paths, wb="camera", units="per_second")
    est, valid = res.radiance.astype(np.float64), res.valid
    err = np.abs(est - env).max(axis=2) / lum
    sun = lum > 100 * np.median(lum)
    lit = sun & valid
    e32 = area_downsample(env, 32)
    m32 = area_downsample(np.where(valid[..., None], est, 0.0), 32)
    full = area_downsample(np.repeat(valid[..., None], 3, axis=2).astype(np.float64), 32)[..., 0] > 0.9999
    err32 = np.abs(m32 - e32).max(axis=2) / e32.max(axis=2)
    return {"hdri": name, "stop_ev": stop, "frames": frames, "noise": noisy,
            "dynamic_range": float(lum.max() / lum.min()),
            "texels_saturated_in_every_frame": int((~valid).sum()), "sun_texels": int(sun.sum()),
            "sun_texels_unsaturated_somewhere": int(lit.sum()),
            "max_err": float(err[valid].max()), "median_err": float(np.median(err[valid])),
            "p99_err": float(np.percentile(err[valid], 99)),
            "mean_ratio": float(np.mean(est[valid] / env[valid])),
            "sun_max_err": float(err[lit].max()) if lit.any() else None,
            "sun_energy_ratio": float(est[lit].sum() / env[lit].sum()) if lit.any() else None,
            "solve_res_median_err": float(np.median(err32[full])), "solve_res_max_err": float(err32[full].max())}


def capture_merges(cap: Path, work: Path) -> dict:
    """ingest's merged target and chrome-ball brackets against their noise-free renders (truth/, same units)."""
    import cv2

    from objcam.image_io import read_exr

    out = {}
    truth = json.loads((cap / "truth" / "truth.json").read_text())
    for kind in ("targets", "probes"):
        for name, info in truth.get(kind, {}).items():
            d = work / "ingest" / kind / name
            if not (d / "image.exr").is_file():
                continue
            est = read_exr(d / "image.exr")[..., :3].astype(np.float64)
            valid = cv2.imread(str(d / "valid.png"), cv2.IMREAD_UNCHANGED) > 127
            clean = read_exr(cap / info["clean_image"])[..., :3].astype(np.float64)
            lum = clean.max(axis=2)
            ok = valid & (lum > 0)
            err = np.abs(est - clean).max(axis=2)[ok] / lum[ok]
            # the well-exposed half: photon noise of the sensor is under ~1% there
            bright = ok & (lum >= np.median(lum[ok]))
            ratio = est[ok].sum() / clean[ok].sum()
            hi = lum > 100 * np.median(lum[lum > 0])  # the sun's reflection (chrome ball) / specular highlights
            hl = hi & valid
            rec = {"frames": len(info.get("frames", [])), "pixels": int(ok.sum()), "flagged": int((~valid).sum()),
                   "median_err": float(np.median(err)),
                   "median_err_bright_half": float(np.median(np.abs(est - clean).max(axis=2)[bright] / lum[bright])),
                   "sum_ratio": float(ratio)}
            if hl.any():
                rec["highlight_pixels"] = int(hl.sum())
                rec["highlight_energy_ratio"] = float(est[hl].sum() / clean[hl].sum())
                rec["highlight_pixels_flagged"] = int((hi & ~valid).sum())
            out[f"{kind}/{name}"] = rec
    return out


# ---------------------------------------------------------------------------------------- the captures


def full_capture(out: Path, overrides: dict | None = None) -> tuple[Path, dict]:
    """The synthetic photographed capture (rendered once per parameter set): (capture folder, render record)."""
    from objcam.synth.full import FullSynthParams, synthesize_full

    params = FullSynthParams(**(E2E_FULL | (overrides or {})))
    key = hashlib.sha256(params.model_dump_json().encode()).hexdigest()[:10]
    root = out / f"full_{key}"
    cap = root / "capture"
    if not (root / "done.json").is_file():
        shutil.rmtree(root, ignore_errors=True)
        load = loadavg()
        t = time.perf_counter()
        summary = synthesize_full(cap, params)
        info = {"seconds": round(time.perf_counter() - t, 1), "load_at_start": load, "load_at_end": loadavg(),
                "params": params.model_dump(mode="json"), "summary": summary}
        (root / "done.json").write_text(json.dumps(info, indent=2))
    return cap, json.loads((root / "done.json").read_text())


def derived_capture(full: Path, dest: Path, albedo_known: bool, probe: bool) -> Path:
    """The rendered capture as ``objcam synth --full`` writes it with ``albedo_known`` and ``probe`` changed: the
    same raws (hard links; neither option changes a rendered file, the probe being rendered after the views and
    the target), capture.toml rewritten (``[albedo]`` with the true object albedo and board texture, or none;
    ``[[probes]]`` or none) and truth.json's flags to match."""
    import tempfile

    from objcam.synth.full import FullSynthParams, _write_manifest, target_names

    truth = json.loads((full / "truth" / "truth.json").read_text())
    params = FullSynthParams(**(truth["params"] | {"albedo_known": albedo_known,
                                                  "probe": probe and truth["params"].get("probe", True)}))
    with tempfile.TemporaryDirectory(prefix="objcam-e2e-") as tmp:
        _write_manifest(Path(tmp), params, target_names(params), truth["albedo"]["support"]["extent"])
        made = {p.relative_to(tmp).as_posix(): p.read_bytes() for p in Path(tmp).rglob("*") if p.is_file()}
    truth["params"] = params.model_dump(mode="json")
    for k in ("object", "support"):
        truth["albedo"][k]["known"] = albedo_known
    if not params.probe:
        truth["probes"] = {}
    made["truth/truth.json"] = json.dumps(truth, indent=2).encode()
    dest.mkdir(parents=True, exist_ok=True)
    link_inputs(full, dest, lambda rel: rel.as_posix() not in made and (params.probe or not (
        rel.parts[0] == "probes" or rel.parts[:2] == ("truth", "probes")
        or rel.parts[:3] == ("truth", "cameras", "probes"))))
    for rel, data in made.items():  # rewritten only when changed (keeps objcam's cache keys and memo valid)
        path = dest / rel
        if not path.is_file() or (path.read_bytes() != data and not _same_exr(path, data)):
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
    return dest


def link_inputs(full: Path, dest: Path, keep) -> None:
    """Hard-link the files of the capture ``full`` into ``dest`` (those not there yet), except objcam's work
    folder and the relative paths ``keep(rel)`` turns down: a derived capture shares the rendered photos."""
    for src in sorted(full.rglob("*")):
        rel = src.relative_to(full)
        if src.is_file() and rel.parts[0] != "objcam" and keep(rel):
            dst = dest / rel
            if not dst.exists():
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.link(src, dst)


def _same_exr(path: Path, data: bytes) -> bool:
    """True when ``path`` is an EXR holding the same pixels as the EXR bytes ``data`` (OpenEXR's multi-threaded
    compression does not always give the same bytes)."""
    import tempfile

    from objcam.image_io import read_exr

    if path.suffix.lower() != ".exr":
        return False
    with tempfile.NamedTemporaryFile(suffix=".exr") as f:
        f.write(data)
        f.flush()
        a, b = read_exr(path), read_exr(Path(f.name))
    return a.shape == b.shape and bool(np.array_equal(a, b))


def known_capture(full: Path, work_raws: Path, dest: Path) -> Path:
    """The known-geometry twin of the photographed capture ``full`` (module doc, step 4), rebuilt when its sources
    changed. Needs ``work_raws/ingest`` (the merged target the from-raws run fits)."""
    from objcam.schemas.capture import CaptureManifest
    from objcam.synth.capture import _toml_value

    m = CaptureManifest.load(full)
    truth = json.loads((full / "truth" / "truth.json").read_text())
    files: dict[str, Path] = {"object.ply": full / "truth" / "object_world.ply"}
    lines = ["# known-geometry twin of a synthetic photographed capture (bench/e2e_bench.py)", "", "[scene]",
             'object = "object.ply"', 'support = "plane"', f"plane_size = {_toml_value(float(m.scene.plane_size))}"]
    toml_full = (full / "capture.toml").read_text()
    if "[albedo]" in toml_full:  # the same albedo declaration as the full capture
        block = toml_full.split("[albedo]", 1)[1].split("\n\n", 1)[0]
        lines += ["", "[albedo]"] + [ln for ln in block.strip().splitlines()]
        for a in (m.albedo.object, m.albedo.support):
            tex = getattr(a, "texture", None)
            if tex:
                files[tex] = full / tex
    for t in m.targets:
        src = work_raws / "ingest" / "targets" / t.name
        files[f"targets/{t.name}.exr"] = src / "image.exr"
        files[f"targets/{t.name}_mask.png"] = src / "valid.png"
        files[f"targets/{t.name}.json"] = full / "truth" / "cameras" / "targets" / f"{t.name}.json"
        lines += ["", "[[targets]]", f'name = "{t.name}"', f'image = "targets/{t.name}.exr"',
                  f'camera = "targets/{t.name}.json"', f'mask = "targets/{t.name}_mask.png"']
        if t.illumination:
            lines.append(f'illumination = "{t.illumination}"')
    # truth/ for evaluate: the envmaps and the albedo it reads
    rels = set(truth.get("envmaps", {}).values())
    for key in ("object", "support"):
        tex = (truth.get("albedo", {}).get(key) or {}).get("texture")
        if tex:
            rels.add(tex)
    for rel in rels:
        files[rel] = full / rel
    files["truth/truth.json"] = full / "truth" / "truth.json"
    toml = "\n".join(lines) + "\n"
    dest.mkdir(parents=True, exist_ok=True)
    for rel, src in files.items():
        dst = dest / rel
        if not dst.is_file() or (dst.read_bytes() != src.read_bytes() and not _same_exr(dst, src.read_bytes())):
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
    if not (dest / "capture.toml").is_file() or (dest / "capture.toml").read_text() != toml:
        (dest / "capture.toml").write_text(toml)
    return dest


# ---------------------------------------------------------------------------------------------- running


def objcam_run(capture: Path, work: Path, sets: list[str], log: Path) -> tuple[int, float, str]:
    """``objcam run CAPTURE --work WORK`` in a subprocess (what a user runs): (exit code, seconds, load at start)."""
    exe = Path(sys.executable).parent / "objcam"
    cmd = [str(exe), "run", str(capture), "--work", str(work), "-q"] + [a for s in sets for a in ("--set", s)]
    load = loadavg()
    t = time.perf_counter()
    with open(log, "a") as f:
        f.write(f"\n$ {' '.join(cmd)}   (load {load})\n")
        f.flush()
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=os.environ | {"OBJCAM_QUIET": "1"}).returncode
    return rc, time.perf_counter() - t, load


def _last_error(log: Path) -> str | None:
    lines = [ln for ln in log.read_text().splitlines() if ln.startswith("objcam: error:")]
    return lines[-1] if lines else None


def stage_records(work: Path, since: float | None = None) -> dict[str, dict]:
    """Each stage's record; ``cached`` (with ``since``, a time.time() before the run): the stage was found in the
    cache, so its seconds are an earlier run's (bench/provenance.py)."""
    from bench.provenance import stage_time

    out = {}
    for s in STAGES:
        p = work / s / "stage.json"
        if p.is_file():
            d = json.loads(p.read_text())
            out[s] = {"seconds": d.get("wall_seconds"), "load": d.get("load_average"), "summary": d.get("summary"),
                      "metrics": d.get("metrics"), "peak_rss_mb": d.get("peak_rss_mb"),
                      "cached": None if since is None else stage_time(work, s, since)["cached"]}
    return out


def camera_errors(cap: Path, work: Path) -> dict:
    from objcam.camera import Camera
    from objcam.sfm.align import camera_difference

    out = {}
    for kind in ("views", "targets", "probes"):
        rows = {}
        for p in sorted((cap / "truth" / "cameras" / kind).glob("*.json")):
            est = work / "sfm" / "cameras" / kind / p.name
            if est.is_file():
                e, t = Camera.load(est), Camera.load(p)
                d, a = camera_difference(e, t)
                rows[p.stem] = {"centre_mm": d * 1000, "rotation_deg": a, "fx_pct": (e.fx / t.fx - 1) * 100}
        n_truth = len(list((cap / "truth" / "cameras" / kind).glob("*.json")))
        if not rows:
            out[kind] = {"registered": f"0/{n_truth}"}
            continue
        c = np.array([r["centre_mm"] for r in rows.values()])
        r = np.array([r["rotation_deg"] for r in rows.values()])
        out[kind] = {"registered": f"{len(rows)}/{n_truth}", "centre_mm_mean": float(c.mean()),
                     "centre_mm_max": float(c.max()), "rotation_deg_mean": float(r.mean()),
                     "rotation_deg_max": float(r.max()),
                     "fx_pct_mean": float(np.mean([x["fx_pct"] for x in rows.values()])),
                     "per_camera": rows if kind != "views" else None}
    return out


def compare(known: dict, raws: dict) -> list[dict]:
    rows = []
    for target in sorted(set(known) & set(raws)):
        for key, label, sign in METRICS:
            k, r = known[target].get(key), raws[target].get(key)
            if k is None or r is None:
                continue
            ratio = r / k if k else float("inf")
            if sign > 0:  # higher is better
                ok = r >= 0.9 * k
            else:
                ok = r <= 1.1 * k or (key == "brightest_angle_deg" and r - k <= ANGLE_SLACK_DEG)
            # what the truth's constant and row-mean maps score on the raws run's mask (objcam/baselines.py)
            base = raws[target].get("baselines") or {}
            rows.append({"target": target, "metric": key, "label": label, "known": k, "raws": r, "ratio": ratio,
                         "within_10pct": bool(ok), "constant": (base.get("constant") or {}).get(key),
                         "row_mean": (base.get("row_mean") or {}).get(key)})
    return rows


# ---------------------------------------------------------------------------------------------- report


def _f(x, nd=3):
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def markdown(res: dict) -> str:
    L = []
    if res.get("hdr"):
        L += ["## HDR merge (5-frame DNG brackets of sunny HDRIs; error per texel relative to its brightest channel)",
              "", "| HDRI | EV step | noise | flagged (sat. in all) | max err | median err | mean ratio | sun max err "
              "| sun energy | 32x64 median / max |", "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
        for h in res["hdr"]:
            L.append(f"| {h['hdri']} | {h['stop_ev']:g} | {'sensor' if h['noise'] else 'none'} | "
                     f"{h['texels_saturated_in_every_frame']} | {h['max_err']:.2%} | {h['median_err']:.3%} | "
                     f"{h['mean_ratio']:.4f} | {_pct(h['sun_max_err'])} | {_f(h['sun_energy_ratio'], 4)} | "
                     f"{h['solve_res_median_err']:.2%} / {h['solve_res_max_err']:.2%} |")
        L.append("")
    if "capture" not in res:
        return "\n".join(L)
    L += [f"Capture: `{res['capture']}` ({res['render'].get('seconds')} s to render, load "
          f"{res['render'].get('load_at_start') or res['render'].get('load')}); stage parameters of every run: "
          f"{res['sets'] or 'defaults'} "
          "(known albedo: also evaluate.scale_invariant=true).", ""]
    for v, r in res["variants"].items():
        L += [f"# Variant {v} (`{r['capture']}`)", ""]
        L += _variant_markdown(r)
    return "\n".join(L)


def _variant_markdown(res: dict) -> list[str]:
    L: list[str] = []
    for run in ("raws", "known"):
        rr = res.get(f"run_{run}")
        if rr and rr.get("rc"):
            L += [f"`objcam run` ({run}) exited {rr['rc']}: `{rr.get('error')}`", ""]
    if res.get("compare"):
        L += ["## Envmap metrics: from raws vs known geometry and cameras", "",
              "| target | metric | known geometry | from raws | ratio | within 10% | constant map | row-mean map |",
              "|---|---|---:|---:|---:|---|---:|---:|"]
        for r in res["compare"]:
            L.append(f"| {r['target']} | {r['label']} | {r['known']:.4f} | {r['raws']:.4f} | {r['ratio']:.3f} | "
                     f"{'yes' if r['within_10pct'] else '**no**'} | {_f(r.get('constant'), 4)} | "
                     f"{_f(r.get('row_mean'), 4)} |")
        L.append("")
        for name in sorted(set(res["metrics_known"]) & set(res["metrics_raws"])):
            k, r = res["metrics_known"][name], res["metrics_raws"][name]
            if "albedo_ssim" in k or "albedo_ssim" in r:
                L += [f"Albedo ({name}, unknown: estimated jointly): SSIM {_f(k.get('albedo_ssim'))} known geometry "
                      f"vs {_f(r.get('albedo_ssim'))} from raws; relative RMSE {_f(k.get('albedo_relative_rmse'))} vs "
                      f"{_f(r.get('albedo_relative_rmse'))}.", ""]
    for run in ("raws", "known"):
        recs = res.get(f"stages_{run}") or {}
        if not recs:
            continue
        L += [f"## Stage times ({'from raws' if run == 'raws' else 'known geometry'})", "",
              "| stage | seconds | load at start | summary |", "|---|---:|---:|---|"]
        for s, r in recs.items():
            summ = (r.get("summary") or "").replace("|", "/").replace("\n", " ")
            secs = _f(r["seconds"], 1) + (" (cached)" if r.get("cached") else "")  # an earlier run's time
            L.append(f"| {s} | {secs} | {_f(r['load'], 2)} | {summ[:160]} |")
        tot = sum(r["seconds"] or 0 for r in recs.values())
        L += [f"| total | {tot:.1f} | | |", ""]
    if res.get("cameras"):
        L += ["## Cameras from the raws against truth (target: 0.5 mm / 0.05 deg)", "",
              "| kind | registered | centre mean / max (mm) | rotation mean / max (deg) | focal error (%) |",
              "|---|---|---:|---:|---:|"]
        for kind, c in res["cameras"].items():
            if c["registered"] == "0/0":
                continue
            L.append(f"| {kind} | {c['registered']} | {_f(c.get('centre_mm_mean'))} / {_f(c.get('centre_mm_max'))} | "
                     f"{_f(c.get('rotation_deg_mean'), 4)} / {_f(c.get('rotation_deg_max'), 4)} | "
                     f"{_f(c.get('fx_pct_mean'), 3)} |")
        L += ["", f"ingest + sfm: {_f(res.get('ingest_sfm_seconds'), 1)} s (target < 120 s); sfm: "
              f"{res.get('sfm_summary')}", ""]
    if res.get("merges"):
        L += ["## Merged brackets of the capture against their noise-free renders", "",
              "| image | frames | pixels | flagged | median err | median err (bright half) | sum ratio | highlight "
              "energy |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for k, m in res["merges"].items():
            L.append(f"| {k} | {m['frames']} | {m['pixels']} | {m['flagged']} | {m['median_err']:.2%} | "
                     f"{m['median_err_bright_half']:.2%} | {m['sum_ratio']:.4f} | "
                     f"{_f(m.get('highlight_energy_ratio'), 4)} |")
        L.append("")
    return L


def _pct(x):
    return "-" if x is None else f"{x:.2%}"


def run_variant(cap: Path, root: Path, v: str, sets: list[str], log: Path, no_known: bool) -> dict:
    """``objcam run`` from the raws of ``cap`` and of its known-geometry twin; the numbers of one variant."""
    res: dict = {"capture": str(cap)}
    work_raws = root / f"work_raws_{v}"
    since = time.time()
    rc, secs, load = objcam_run(cap, work_raws, sets, log)
    res["run_raws"] = {"rc": rc, "seconds": round(secs, 1), "load_at_start": load}
    if rc != 0:
        res["run_raws"]["error"] = _last_error(log)
    res["stages_raws"] = stage_records(work_raws, since)
    if (work_raws / "sfm" / "stage.json").is_file():
        res["cameras"] = camera_errors(cap, work_raws)
        st = res["stages_raws"]
        res["ingest_sfm_seconds"] = (st["ingest"]["seconds"] or 0) + (st["sfm"]["seconds"] or 0)
        res["sfm_summary"] = st["sfm"]["summary"]
    if (work_raws / "ingest" / "stage.json").is_file():
        res["merges"] = capture_merges(cap, work_raws)
    metrics_raws = work_raws / "evaluate" / "metrics.json"
    if rc != 0 or not metrics_raws.is_file():
        print(f"objcam run from raws failed (exit {rc}); see {log}", file=sys.stderr)
    if not no_known and (work_raws / "ingest" / "stage.json").is_file():
        known = known_capture(cap, work_raws, root / f"known_{v}")
        since_k = time.time()
        rc_k, secs_k, load_k = objcam_run(known, root / f"work_known_{v}", sets, log)
        res["run_known"] = {"rc": rc_k, "seconds": round(secs_k, 1), "load_at_start": load_k}
        res["stages_known"] = stage_records(root / f"work_known_{v}", since_k)
        metrics_known = root / f"work_known_{v}" / "evaluate" / "metrics.json"
        if metrics_raws.is_file() and metrics_known.is_file():
            mk, mr = json.loads(metrics_known.read_text()), json.loads(metrics_raws.read_text())
            res["metrics_known"], res["metrics_raws"] = mk, mr
            res["compare"] = compare(mk, mr)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/out/e2e"))
    ap.add_argument("--downsample", type=int, default=4, help="transport.downsample of both runs")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="STAGE.PARAM=VALUE for both runs")
    ap.add_argument("--hdr-only", action="store_true", help="only the HDR merge numbers (seconds)")
    ap.add_argument("--no-hdr", action="store_true")
    ap.add_argument("--no-known", action="store_true", help="skip the known-geometry run")
    ap.add_argument("--with-probe", action="store_true", help="keep the chrome ball (and so the probe stage) in the "
                    "runs from raws; default: the capture without it (evaluate compares with truth/ either way)")
    ap.add_argument("--albedo", nargs="+", choices=("known", "unknown"), default=["known", "unknown"],
                    help="albedo declaration(s) of the runs (capture.toml [albedo]), each with its own known twin")
    ap.add_argument("--views", type=int, default=E2E_FULL["n_views"])
    ap.add_argument("--width", type=int, default=E2E_FULL["width"])
    ap.add_argument("--height", type=int, default=E2E_FULL["height"])
    ap.add_argument("--synth", default="{}", help="more FullSynthParams as JSON")
    ap.add_argument("--write", action="store_true", help="replace the e2e block of bench/results.md")
    a = ap.parse_args(argv)
    os.environ.setdefault("OBJCAM_QUIET", "1")
    res: dict = {"load_at_start": loadavg(), "machine_cores": os.cpu_count()}
    if not a.no_hdr:
        res["hdr"] = [hdri_merge(n, s, noisy) for n, s in (("city", 2.0), ("sunrise", 2.0), ("sunrise", 3.0))
                      for noisy in (False, True)]
    if a.hdr_only:
        print(markdown(res))
        return 0

    overrides = {"n_views": a.views, "width": a.width, "height": a.height} | json.loads(a.synth)
    cap, render = full_capture(a.out, overrides)
    root = cap.parent
    sets = [f"transport.downsample={a.downsample}"] + a.sets
    res.update({"capture": str(cap), "render": render, "sets": sets, "variants": {}})
    log = root / "run.log"

    for albedo in a.albedo:
        v = f"albedo-{albedo}" + ("" if a.with_probe else "_no-probe")
        cap_v = derived_capture(cap, root / f"capture_{v}", albedo == "known", a.with_probe)
        # photographed units are decoded value per second = sensor gain x radiance, a gain objcam cannot know: with
        # known albedo evaluate must compare up to one global scale (unknown albedo: a scale per channel already)
        vsets = sets + (["evaluate.scale_invariant=true"] if albedo == "known" else [])
        res["variants"][v] = run_variant(cap_v, root, v, vsets, log, a.no_known)
    res["load_at_end"] = loadavg()
    (root / "results.json").write_text(json.dumps(res, indent=2, default=str))
    if a.write:  # the raw rows behind the block, committed beside results.md
        Path("bench/e2e_rows.json").write_text(json.dumps(res, indent=1, default=str) + "\n")
    md = markdown(res)
    (root / "results.md").write_text(md + "\n")
    print(md)
    if a.write:
        from bench.sections import invocation, write_section

        # its own headings sit under the results page's section: one level deeper
        body = "\n".join("###" + ln if ln.startswith("#") else ln for ln in md.splitlines())
        write_section("e2e", f"{invocation('bench.e2e_bench', argv)}.\n\n{body}",
                      "End to end from raw photos (issues 3 and 4)")
    print(f"load average: {res['load_at_start']} at start, {res['load_at_end']} at end (2 cores); {root}")
    ok = all(bool(r.get("compare")) and all(c["within_10pct"] for c in r["compare"])
             for r in res["variants"].values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
