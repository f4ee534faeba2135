"""Benchmark of issue 4: geometry and texture from photos on the default view ring.

    .venv/bin/python -m bench.geometry_bench [--spp N] [--views N] [--elevations A B ...] [--width W --height H]
                                             [--out DIR]

Renders (once; cached under ``--out`` by its parameters; ~30 min on 2 busy cores) the default ring of
objcam.synth.views (the 8 cm bunny on the A3 board under ``forest``, 24 views at 800 x 600 on rings at 30 and 50
degrees elevation, 32 spp) as linear views with cameras perturbed by SfM-sized
errors (0.2 mm, 0.02 deg) and sparse board points (0.15 mm noise, 3% outliers), then runs the geometry stage
twice (known shape given in mm, y up, yawed: registered; and no shape: reconstructed) and the texture stage,
and prints a markdown table: registration error (mean vertex distance to truth), plane deviation, Chamfer
distance of the reconstruction (% of height), stage times, albedo errors, and the load average. The stages'
folders and ``results.json`` are written beside the inputs (``--out``/inputs_<key>/).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np


def _load() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def _inputs(out: Path, params):
    from objcam.synth.geometry_inputs import SyntheticInputs, write_inputs

    key = hashlib.sha256(params.model_dump_json().encode()).hexdigest()[:12]
    root = out / f"inputs_{key}"
    if not (root / "done").is_file():
        shutil.rmtree(root, ignore_errors=True)
        t = time.perf_counter()
        write_inputs(root, params)
        (root / "done").write_text(f"{time.perf_counter() - t:.1f}")
    return SyntheticInputs(capture=root / "capture", ingest=root / "ingest", sfm=root / "sfm", truth=root / "truth")


def _stage(mod, capture, upstream, out: Path, params=None):
    from objcam.pipeline.stage import StageInputs

    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    load = _load()
    t = time.perf_counter()
    res = mod.run(StageInputs(capture=capture, upstream=upstream, out=out, quiet=True), params or mod.Params())
    return res, time.perf_counter() - t, load


def main(argv: list[str] | None = None) -> int:
    from objcam.geometry.chamfer import chamfer
    from objcam.scene import MeshData, load_mesh
    from objcam.stages import geometry, texture
    from objcam.synth.geometry_inputs import albedo_error
    from objcam.synth.views import ViewRingParams

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--elevations", type=float, nargs="+", default=None, help="ring elevations, degrees")
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--height", type=int, default=600)
    ap.add_argument("--out", default="bench/out/geometry")
    ap.add_argument("--write", action="store_true", help="replace the geometry block of bench/results.md")
    a = ap.parse_args(argv)
    os.environ.setdefault("OBJCAM_QUIET", "1")
    out = Path(a.out)
    ring = {"elevations_deg": a.elevations} if a.elevations else {}
    params = ViewRingParams(spp=a.spp, n_views=a.views, width=a.width, height=a.height, **ring)
    inp = _inputs(out, params)
    runs = inp.capture.parent  # the stages' folders and results.json sit beside the inputs they were run on
    truth = MeshData.load_npz(inp.truth / "object.npz")
    height = float(truth.bbox[1][2] - truth.bbox[0][2])
    up = {"ingest": inp.ingest, "sfm": inp.sfm}

    # known shape
    g_res, g_time, g_load = _stage(geometry, inp.capture, up, runs / "geometry_known")
    reg = g_res.metrics["registration"]
    sil = reg["silhouette"]
    w = np.asarray(reg["world_from_model"])
    v = load_mesh(inp.capture / "object.ply").vertices.astype(np.float64) @ w[:3, :3].T + w[:3, 3]
    v[:, 2] -= v[:, 2].min()
    reg_err = np.linalg.norm(v - truth.vertices.astype(np.float64), axis=1)
    t_res, t_time, t_load = _stage(texture, inp.capture, {**up, "geometry": runs / "geometry_known"},
                                   runs / "texture_known")
    alb = albedo_error(runs / "texture_known", inp.truth)

    # reconstruction: the same capture without scene.object
    cap2 = runs / "capture_reconstruct"
    shutil.rmtree(cap2, ignore_errors=True)
    cap2.mkdir(parents=True)
    toml = (inp.capture / "capture.toml").read_text().replace('object = "object.ply"\n', "")
    (cap2 / "capture.toml").write_text(toml)
    r_res, r_time, r_load = _stage(geometry, cap2, up, runs / "geometry_reconstruct")
    rec = MeshData.load_npz(runs / "geometry_reconstruct" / "object.npz")
    ch = chamfer(rec, truth, 100_000)
    rm = r_res.metrics

    m = g_res.metrics
    rows = [
        ("known-shape registration error, mean (max) vertex distance", f"{reg_err.mean() * 1e3:.2f} mm "
         f"({reg_err.max() * 1e3:.2f} mm)", "<= 0.5 mm"),
        ("registration residual to the hull (trimmed RMS, before the silhouette fit)", f"{reg['rms_mm']:.2f} mm",
         ""),
        ("silhouette fit: outline residual RMS / mask offset / outline on the masks",
         f"{sil['rms_px']:.2f} px / {sil['offset_px']:+.2f} px / {100 * sil['agree_fraction']:.0f}%", ""),
        ("plane: max deviation from z = 0 over the volume", f"{m['plane_deviation_mm']:.3f} mm", "<= 0.25 mm"),
        ("plane: inlier RMS (points carry 0.15 mm noise)", f"{m['plane']['rms_mm']:.3f} mm", ""),
        ("reconstructed shape: Chamfer to truth (mean of both ways)",
         f"{ch.mean * 1e3:.3f} mm = {100 * ch.mean / height:.3f}% of height", "<= 1% of height"),
        ("reconstructed shape: 95th percentile distance", f"{ch.p95 * 1e3:.2f} mm", ""),
        ("reconstruction: outline offset measured / pixels marked ambiguous",
         f"{rm.get('outline_offset_px', 0):+.2f} px / {rm.get('ambiguous_pixels', 0)}", ""),
        ("geometry (known shape) + texture time", f"{g_time:.1f} s + {t_time:.1f} s = {g_time + t_time:.1f} s",
         "< 180 s"),
        ("geometry (reconstruction) time", f"{r_time:.1f} s", ""),
        ("support albedo abs. error: median / 90th pct (board)", f"{alb.support_median:.3f} / {alb.support_p90:.3f}",
         ""),
        ("plain-paper albedo abs. error, median", f"{alb.paper_median:.3f}", ""),
        ("object albedo bias (estimate - truth 0.6), median", f"{alb.object_bias:+.3f}", ""),
        ("load average at the stages' start (2 cores)", f"{g_load:.1f} / {t_load:.1f} / {r_load:.1f}", ""),
    ]
    md = "\n".join([f"View ring: {params.n_views} views at {params.width} x {params.height} on rings at "
                    f"{', '.join(f'{e:g}' for e in params.elevations_deg)} deg, {params.spp} spp, bunny "
                    f"{height * 100:.0f} cm, cameras perturbed (0.2 mm, 0.02 deg).", "",
                    "| measure | result | target |", "|---|---:|---|"] + [f"| {r[0]} | {r[1]} | {r[2]} |" for r in rows])
    print(md)
    if a.write:
        from bench.sections import invocation, write_section

        write_section("geometry", f"{invocation('bench.geometry_bench', argv)}.\n\n{md}", "Geometry and texture (issue 4)")
    (runs / "results.json").write_text(json.dumps({"rows": rows, "ring": params.model_dump(), "geometry": m,
                                                   "texture": t_res.metrics, "reconstruct": r_res.metrics},
                                                  indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
