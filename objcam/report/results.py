"""The report's result panels: each target's envmap beside its truth and chrome ball (for
:mod:`objcam.report.envmap_view`), the fit's verdict line, the parameters every stage ran with and links to the
artifact files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from objcam.report import html as H


def _json(path: Path) -> Any:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def target_maps(capture: Path, up: dict[str, Path], target: str, illumination: str | None,
                m: dict | None) -> tuple[list[tuple[str, np.ndarray]], str, int]:
    """[(caption, (H, 2H, 3) linear map in the standard file convention)]: the estimate (times evaluate's best-fit
    scale when it compared up to scale), the truth (when the capture has one) and the chrome ball (scaled to the
    estimate's mean over the texels it shows); a note on the scales; the index of the exposure reference (the
    truth, else the estimate)."""
    from objcam.envmap import resample_to_height, to_file
    from objcam.image_io import read_exr

    path = up["solve"] / target / "envmap.exr"
    if not path.is_file():
        return [], "", 0
    est = read_exr(path)[..., :3].astype(np.float64)
    h = est.shape[0]
    notes, maps = [], []
    m = m if isinstance(m, dict) else {}
    scale = np.asarray(m.get("scale_channels", m.get("scale", 1.0)) or 1.0, np.float64)
    if not np.allclose(scale, 1.0):
        est = est * scale
        notes.append(f"estimate x {H.fmt(scale.tolist() if scale.ndim else float(scale))} (evaluate's best fit)")
    maps.append(("estimate" if not notes else "estimate (scaled)", est))
    if m.get("truth_source") == "truth" and m.get("truth_file"):
        tp = capture / m["truth_file"]
        if tp.is_file():
            truth = resample_to_height(read_exr(tp)[..., :3].astype(np.float64), h)
            maps.append((f"truth (area-averaged to {h} x {2 * h})", truth))
    if "probe" in up:
        from objcam.probe.truth import probe_truth

        got = probe_truth(up["probe"], illumination or target, h)
        if got is not None:
            probe, valid = to_file(got[0]), to_file(got[1])
            probe = np.where(valid[..., None], probe, 0.0)
            s = est[valid].mean() / max(probe[valid].mean(), 1e-30) if valid.any() else 1.0
            maps.append(("chrome ball (scaled to the estimate's mean over the texels it shows)", probe * s))
    return maps, "; ".join(notes), 1 if len(maps) > 1 and maps[1][0].startswith("truth") else 0


VERDICT_COLOURS = {"green": "#1b7f3a", "yellow": "#9a6b00", "red": "#b3261e"}


def verdict_line(solve: dict | None, m: dict | None) -> str:
    """The solve's verdict (objcam.solvers.plan.verdict: grade and reasons, from the data alone) with the fit's
    relative image residual, and (with a truth) whether the estimate beats the truth's row-mean map."""
    m = m if isinstance(m, dict) else {}
    solve = solve if isinstance(solve, dict) else {}
    parts = []
    v = solve.get("verdict") if isinstance(solve.get("verdict"), dict) else m.get("verdict")
    if isinstance(v, dict) and v.get("grade"):
        g = str(v["grade"])
        why = "; ".join(str(r) for r in v.get("reasons") or []) or "the model explains the photo to its noise"
        parts.append(f'verdict (from the data alone) <strong style="color:{VERDICT_COLOURS.get(g, "inherit")}">'
                     f"{H.esc(g)}</strong>: {H.esc(why)}")
    res = solve.get("relative_image_residual")
    parts.append(f"fit residual (relative, image) <strong>{H.esc(H.fmt(res))}</strong>")
    beats = (m.get("beats_row_mean") or {}).get("ssim")
    if beats is not None:
        parts.append("beats the truth's row-mean map in SSIM" if beats else
                     "does <strong>not</strong> beat the truth's row-mean map in SSIM")
    return f'<p class="verdict">Quality: {"; ".join(parts)}.</p>'


def _flat(d: dict, prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for k, v in d.items():
        out += _flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [(prefix + k, v)]
    return out


def params_section(up: dict[str, Path]) -> str:
    """Every stage's parameters as it ran (stage.json), in a collapsed table."""
    rows = []
    for stage, d in up.items():
        rec = _json(d / "stage.json")
        if isinstance(rec, dict) and isinstance(rec.get("params"), dict):
            rows += [(stage, k, json.dumps(v)) for k, v in _flat(rec["params"])]
    if not rows:
        return ""
    return (f'<section id="params"><h2>Parameters used</h2><details><summary>{len(rows)} parameters of '
            f"{len({r[0] for r in rows})} stages (objcam params lists their meaning; [params.STAGE] in capture.toml "
            "keeps a setting)</summary>" + H.table(("stage", "parameter", "value"), rows) + "</details></section>")


def links_section(up: dict[str, Path], targets: list[str]) -> str:
    """Relative links from report/index.html to the artifact files (valid while the page sits in the work
    folder)."""
    items = []
    for t in targets:
        for rel in (f"solve/{t}/envmap.exr", f"solve/{t}/envmap.png", f"solve/{t}/prediction.exr",
                    f"solve/{t}/solve.json"):
            stage = rel.split("/", 1)[0]
            if stage in up and (up[stage] / rel.split("/", 1)[1]).is_file():
                items.append(f'<li><a href="../{H.esc(rel)}"><code>{H.esc(rel)}</code></a></li>')
    for rel in ("evaluate/metrics.json", "analysis/analysis.json", "sfm/report.json", "probe/probes.json",
                "geometry/geometry.json"):
        stage, name = rel.split("/", 1)
        if stage in up and (up[stage] / name).is_file():
            items.append(f'<li><a href="../{H.esc(rel)}"><code>{H.esc(rel)}</code></a></li>')
    return (f'<section id="files"><h2>Files</h2><p class="meta">Relative to this page\u2019s work folder; '
            "<code>objcam export CAPTURE OUT</code> writes them for other tools (EXR/HDR envmaps, PLY/OBJ/GLB "
            f"meshes, cameras, Mitsuba and Blender scenes).</p><ul>{''.join(items)}</ul></section>")
