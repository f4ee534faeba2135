"""Stage ``report``: one self-contained HTML page per capture, ``report/index.html``.

Every image is inlined as a base64 PNG data URI (no external resources; one inline script: the envmaps' exposure
slider), so the one file can be mailed. A photographed capture starts with how it became a scene (ingest, SfM,
geometry, texture, probe: objcam.report.capture). Per target: the envmap large, beside the truth and the chrome
ball at one exposure with a slider, direction labels and the horizon (objcam.report.envmap_view), the quality
line; the overview (target photo | truth | estimate) and the error map; prediction and residual; the analysis
images of its camera group (leverage, uncertainty, spectrum, gains) and its Cook's distance; with unknown albedo the recovered albedo, its mask and
the comparison with the true albedo. A speed-against-error plot places the run among the benchmark's settings
(``make bench``'s results.json).  Then tables of the stages (time, peak memory, summary,
key) and of the metrics (evaluate, solve, analysis), the parameters every stage ran with, objcam's version and
links to the artifact files. Missing optional artifacts get a note, never a crash.
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from objcam.image_io import atomic_write_text
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.report import html as H
from objcam.report import envmap_view, results

NAME = "report"
DEPS = ("scene", "transport", "solve", "evaluate", "analysis")
OPTIONAL_DEPS = ("ingest", "sfm", "geometry", "texture", "probe")  # a photographed capture's story
VERSION = "3"
CODE_DEPS = ("objcam.report.html", "objcam.report.speed", "objcam.report.capture", "objcam.report.envmap_view",
             "objcam.report.results")

EXPOSURE_NOTE = ("Envmaps share one exposure: divided by the truth's 99th percentile (over solved texels; its maximum "
                 "where a flat background fills that percentile), clipped to 1, gamma 1/2.2; texels the solve did "
                 "not model are dimmed.")
EVAL_KEYS = ("ssim", "relative_rmse", "relative_rmse_solid_angle", "tonemapped_rmse", "brightest_angle_deg",
             "scale", "best_scale", "albedo_relative_rmse", "albedo_ssim")
SOLVE_KEYS = ("method", "texels", "pixels_used", "pixels_excluded", "iterations", "kkt_residual_max",
              "solve_seconds", "relative_image_residual")
GROUP_KEYS = ("pixels", "texels", "effective_rank", "entropy_effective_rank", "ridge_dof", "condition_number",
              "leverage_max", "uncertainty_mean_upper", "uncertainty_worst_upper")


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    max_image_width: int = Field(1200, ge=64, description="wider PNGs are downscaled (area) before inlining, "
                                                          "to keep the page small")
    bench_results: str | None = Field(None, description="the benchmark's results.json for the speed-against-error "
                                      "plot; None: the copy shipped in objcam/assets (bench_results.json, what "
                                      "`make bench` wrote last), else bench/out/results.json of a source "
                                      "checkout, if there is one")


# The benchmark results it plots live in the repository, not the capture (objcam.pipeline.inputs' confinement).
READS_OUTSIDE_CAPTURE = True


def input_files(capture: Path) -> list[Path]:
    """The default benchmark results: a new benchmark run redraws the speed-against-error plot."""
    from objcam.report.speed import find_bench_results

    found = find_bench_results()
    return [found] if found is not None else []


def _json(path: Path) -> Any:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def _target_names(up: dict[str, Path]) -> list[str]:
    recs = _json(up["scene"] / "targets.json") if "scene" in up else None
    if isinstance(recs, list):
        return [r["name"] for r in recs if isinstance(r, dict) and "name" in r]
    solve = up.get("solve")
    return sorted(p.name for p in solve.iterdir() if p.is_dir()) if solve and solve.is_dir() else []


def _stage_table(up: dict[str, Path]) -> tuple[str, list[str]]:
    rows, names = [], []
    for name in [n for n in OPTIONAL_DEPS if n in up] + list(DEPS):
        info = _json(up[name] / "stage.json") if name in up else None
        names.append(name)
        if not isinstance(info, dict):
            rows.append((name, None, None, "no stage.json", None, None))
            continue
        rows.append((name, info.get("wall_seconds"), info.get("peak_rss_mb"), info.get("summary") or "",
                     (info.get("key") or "")[:12], info.get("finished")))
    return H.table(("stage", "wall time (s)", "peak RSS (MB)", "summary", "key", "finished"), rows), names


def _albedo_panel(sd: Path, ed: Path, m: dict | None, png) -> str:
    """The estimated albedo of a joint solve (nothing when the albedo was known)."""
    est = png(sd / "albedo.png")
    if est is None:
        return ""
    parts = ["<h3>Recovered albedo</h3>"]
    info = _json(sd / "solve.json")
    uniform = info.get("albedo_uniform") if isinstance(info, dict) else None
    if uniform:  # surfaces capture.toml declares one colour: one value each, not one per pixel
        said = "; ".join(f"{name} ({', '.join(H.fmt(v) for v in rgb)})" for name, rgb in uniform.items())
        parts.append(f"<p>One colour each, as capture.toml declares (<code>\"uniform\"</code>): {H.esc(said)}, "
                     "at the solve's scale.</p>")
    if m and m.get("albedo_relative_rmse") is not None:
        parts.append(f"<p>Albedo relative RMSE <strong>{H.esc(H.fmt(m['albedo_relative_rmse']))}</strong>, SSIM "
                     f"<strong>{H.esc(H.fmt(m.get('albedo_ssim')))}</strong> (after the best-fit scale per "
                     "channel: with unknown albedo, albedo and envmap are known only up to one scale).</p>")
    parts.append(H.grid([
        H.figure(est, "estimated albedo per pixel (linear albedo clipped to [0, 1], gamma 1/2.2, no exposure "
                 "scaling; up to one scale per channel)"),
        H.figure(png(sd / "albedo_mask.png"), "where the albedo was unknown and estimated (white)"),
        H.figure(png(ed / "albedo_compare.png"), "true albedo | estimate (best-fit scale) | 4 x |error| "
                 "(gamma 1/2.2)", missing="no albedo truth to compare with (evaluate/<target>/albedo_compare.png)"),
    ]))
    return "".join(parts)


def _speed_section(up: dict[str, Path], targets: list[str], metrics: dict, bench_path: str | None) -> str:
    """Speed against error: the benchmark's settings with this run's targets overlaid."""
    from objcam.report.speed import bench_points, find_bench_results, load_results, speed_error_png

    parts = ['<section id="speed"><h2>Speed against error</h2>']
    found = find_bench_results(bench_path)
    results = load_results(found) if found is not None else None
    points = bench_points(results) if results else []
    transport = _json(up["transport"] / "stage.json") if "transport" in up else None
    a_seconds = (transport or {}).get("wall_seconds") if isinstance(transport, dict) else None
    mine = []
    for t in targets:
        s = _json(up["solve"] / t / "solve.json") if "solve" in up else None
        m = metrics.get(t) if isinstance(metrics, dict) else None
        if isinstance(s, dict) and isinstance(m, dict) and a_seconds is not None and s.get("solve_seconds"):
            mine.append({"name": t, "seconds": float(a_seconds) + float(s["solve_seconds"]),
                         "ssim": m.get("ssim"), "relative_rmse": m.get("relative_rmse")})
    if not points and not mine:
        parts.append(H.note("no benchmark results (run `make bench`) and no metrics for this run: nothing to plot"))
    else:
        cap = ("time to build A plus solve against envmap SSIM and relative RMSE; colours: HDRI, markers: solve "
               "method, stars: this capture's targets (its transport wall time + solve time)")
        if points:
            cap += f"; benchmark: {found.name} ({len(points)} runs)"
        else:
            cap += "; no benchmark results found (run `make bench`)"
        parts.append(H.figure(speed_error_png(points, mine), cap, plot=True))
    parts.append("</section>")
    return "".join(parts)


def _target_section(t: str, up: dict[str, Path], metrics: dict, group: str | None, width: int,
                    seen_groups: set[str], capture: Path, illumination: str | None) -> str:
    png = lambda p: H.read_png(p, width)  # noqa: E731
    sd, ed, ad = up["solve"] / t, up["evaluate"] / t, up["analysis"]
    parts = [f'<section id="target-{H.esc(t)}"><h2>Target {H.esc(t)}</h2>']
    m = metrics.get(t) if isinstance(metrics, dict) else None
    maps, note, ref = results.target_maps(capture, up, t, illumination, m)
    parts.append(envmap_view.envmap_panel(t, maps, note, ref))
    parts.append(results.verdict_line(_json(sd / "solve.json"), m))
    if isinstance(m, dict):
        parts.append(f"<p>SSIM <strong>{H.esc(H.fmt(m.get('ssim')))}</strong>, relative RMSE "
                     f"<strong>{H.esc(H.fmt(m.get('relative_rmse')))}</strong>, brightest-source angle "
                     f"{H.esc(H.fmt(m.get('brightest_angle_deg')))}&nbsp;deg.</p>")
        rm = (m.get("baselines") or {}).get("row_mean")
        if isinstance(rm, dict):  # issue 28: what a map knowing only each elevation's brightness scores
            parts.append(f"<p>The truth's row-mean map (no azimuth) scores SSIM {H.esc(H.fmt(rm.get('ssim')))} and "
                         f"relative RMSE {H.esc(H.fmt(rm.get('relative_rmse')))}; the constant map SSIM "
                         f"{H.esc(H.fmt((m['baselines'].get('constant') or {}).get('ssim')))}.</p>")
    parts.append("<h3>Overview and error</h3>")
    overview = png(ed / "overview.png")
    if overview is not None:
        parts.append(H.grid([
            H.figure(overview, "target photo | true envmap (area-averaged) | recovered envmap. " + EXPOSURE_NOTE,
                     plot=True),
            H.figure(png(ed / "compare.png"), "truth | estimate | |error| (the scores' exposure, clipped, gamma "
                     "1/2.2; unsolved texels dimmed)", missing="no error map (evaluate/compare.png)"),
        ], wide=True))
    else:
        parts.append(H.note("No truth for this target: the recovered envmap is shown alone "
                            "(its own 99th percentile, clipped, gamma 1/2.2)."))
        parts.append(H.grid([
            H.figure(png(sd / "target.png"), "target photo (pooled; 99th percentile, clipped, gamma 1/2.2)"),
            H.figure(png(sd / "envmap.png"), "recovered envmap (lat-long, zenith at top; own 99th percentile, "
                     "clipped, gamma 1/2.2)"),
        ]))
    parts.append(_albedo_panel(sd, ed, m if isinstance(m, dict) else None, png))
    # fit
    parts.append("<h3>Fit</h3>")
    parts.append(H.grid([
        H.figure(png(sd / "target.png"), "target fitted (pooled); exposure: its 99th percentile, gamma 1/2.2"),
        H.figure(png(sd / "prediction.png"), "prediction A x (same exposure as the target)"),
        H.figure(png(sd / "residual.png"), "|residual| = |target - prediction| (same exposure)"),
    ]))
    # analysis
    parts.append("<h3>What the object-camera can see</h3>")
    figs = [H.figure(png(ad / t / "cooks.png"), "Cook's distance per pixel (influence on the fit, log scale)",
                     plot=True, missing="no Cook's distance (analysis/<target>/cooks.png)")]
    if group is None:
        figs.append(H.note("camera group unknown: no leverage / uncertainty / spectrum / gain images"))
    elif group in seen_groups:
        figs.append(H.note(f"leverage, uncertainty, spectrum and gains: shared camera group {group}, shown "
                           "with its first target above"))
    else:
        seen_groups.add(group)
        gd = ad / group
        for fname, cap in (("leverage.png", "leverage h_ii per pixel (log)"),
                           ("uncertainty.png", "per-texel uncertainty sqrt(diag((A^T A + lr I)^-1)) (log)"),
                           ("spectrum.png", "singular spectrum of A, effective rank"),
                           ("gains.png", "gain images: how each pixel moves one texel")):
            figs.append(H.figure(png(gd / fname), f"{cap} [camera group {group}]", plot=True,
                                 missing=f"no {fname} for camera group {group}"))
    parts.append(H.grid(figs, wide=True))
    parts.append("</section>")
    return "".join(parts)


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    up = inputs.upstream
    capture = Path(inputs.capture)
    targets = _target_names(up)
    index = _json(up["transport"] / "index.json") if "transport" in up else None
    groups = (index or {}).get("targets", {}) if isinstance(index, dict) else {}
    metrics = _json(up["evaluate"] / "metrics.json") if "evaluate" in up else None
    has_truth = isinstance(metrics, dict) and metrics.get("truth", True) is not False and bool(metrics)
    analysis = _json(up["analysis"] / "analysis.json") if "analysis" in up else None
    analysis = analysis if isinstance(analysis, dict) else {}

    from objcam.report.capture import capture_sections

    body: list[str] = []
    photo_html, photo_toc = capture_sections(up, params.max_image_width, capture)
    toc = "".join(f'<li><a href="#{s}">{H.esc(title)}</a></li>' for s, title in photo_toc)
    toc += "".join(f'<li><a href="#target-{H.esc(t)}">target {H.esc(t)}</a></li>' for t in targets)
    body.append(f"<nav><ul>{toc}</ul><p><a href=\"#speed\">Speed against error</a> \u00b7 "
                "<a href=\"#stages\">Stages</a> \u00b7 <a href=\"#metrics\">Metrics</a> \u00b7 "
                "<a href=\"#params\">Parameters</a> \u00b7 <a href=\"#files\">Files</a></p></nav>")
    body.append(photo_html)
    if not has_truth:
        body.append(H.note("This capture has no truth/ (evaluate wrote {\"truth\": false}): no accuracy metrics "
                           "or truth comparison."))
    seen: set[str] = set()
    illum = {r.get("name"): r.get("illumination") for r in (_json(up["scene"] / "targets.json") or [])
             if isinstance(r, dict)} if "scene" in up else {}
    for t in targets:
        body.append(_target_section(t, up, metrics if has_truth else {}, groups.get(t), params.max_image_width,
                                    seen, capture, illum.get(t)))

    body.append(_speed_section(up, targets, metrics if has_truth else {}, params.bench_results))
    stage_html, stage_names = _stage_table(up)
    body.append(f'<section id="stages"><h2>Stages</h2>{stage_html}</section>')

    body.append('<section id="metrics"><h2>Metrics</h2><h3>Accuracy against the truth (evaluate)</h3>')
    if has_truth:
        rows = [(t, *[(metrics.get(t) or {}).get(k) for k in EVAL_KEYS]) for t in targets]
        body.append(H.table(("target", *EVAL_KEYS), rows))
        body.append(f"<p class=\"meta\">{H.esc(EXPOSURE_NOTE)} relative_rmse: RMSE / mean of the truth over "
                    "solved texels.</p>")
    else:
        body.append(H.note("no truth: nothing to compare"))
    body.append("<h3>Solve</h3>")
    srows = []
    for t in targets:
        s = _json(up["solve"] / t / "solve.json")
        srows.append((t, *[(s or {}).get(k) for k in SOLVE_KEYS]) if isinstance(s, dict)
                     else (t, *(["missing solve.json"] + [None] * (len(SOLVE_KEYS) - 1))))
    body.append(H.table(("target", *SOLVE_KEYS), srows))
    body.append("<h3>Analysis (per camera group)</h3>")
    ag = analysis.get("groups") or {}
    if ag:
        body.append(H.table(("group", *GROUP_KEYS), [(g, *[v.get(k) for k in GROUP_KEYS]) for g, v in ag.items()]))
    else:
        body.append(H.note("no analysis.json groups"))
    at = analysis.get("targets") or {}
    if at:
        body.append(H.table(("target", "cooks_max", "cooks_over_4_over_M"),
                            [(t, v.get("cooks_max"), v.get("cooks_over_4_over_M")) for t, v in at.items()]))
    body.append("</section>")
    body.append(results.params_section(up))
    body.append(results.links_section(up, targets))

    from objcam import __version__

    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    subtitle = (f"capture <code>{H.esc(capture)}</code> \u00b7 {len(targets)} target(s) \u00b7 written {H.esc(now)}"
                f" \u00b7 objcam {H.esc(__version__)}")
    text = H.page(f"objcam report: {capture.name}", "".join(body), subtitle=subtitle, css=envmap_view.CSS,
                  script=envmap_view.SCRIPT)
    atomic_write_text(inputs.out / "index.html", text)
    size_mb = len(text.encode("utf-8")) / 1e6
    return StageOutputs(metrics={"bytes": len(text.encode("utf-8")), "targets": len(targets),
                                 "stages": stage_names},
                        summary=f"report/index.html: {len(targets)} target(s), {size_mb:.2f} MB")
