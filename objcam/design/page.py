"""The ``objcam design`` HTML page: the comparison figure and the numbers table, self-contained (the figure
inlined as a PNG data URI), built from the report stage's helpers (:mod:`objcam.report.html`)."""

from __future__ import annotations

from pathlib import Path

from objcam.report import html as H

#: (key in design.json, column heading) of the table, in order
COLUMNS = (
    ("uncertainty_mean", "mean uncertainty (upper sky)"),
    ("uncertainty_worst", "worst uncertainty"),
    ("spread", "spread worst/mean"),
    ("azimuth_cv", "azimuthal variation (CV)"),
    ("fraction_resolved", "fraction resolved"),
    ("uncertainty_zenith", "zenith band mean"),
    ("uncertainty_horizon", "horizon band mean"),
    ("effective_rank", "effective rank"),
    ("entropy_effective_rank", "entropy eff. rank"),
    ("leverage_max", "max leverage"),
    ("pixels", "pixels"),
    ("texels", "texels"),
)


def table_rows(results: dict) -> list[tuple]:
    """One row per occluder of ``design.json``'s ``objects``: its name, then the :data:`COLUMNS` values."""
    return [(name, *[r["numbers"].get(k) for k, _ in COLUMNS]) for name, r in results["objects"].items()]


def write_page(path: Path, results: dict, figure_png: Path) -> Path:
    """``index.html``: what was compared and how, the figure, the table and the per-occluder files."""
    p, setup = results["params"], results["setup"]
    body = [
        "<section><h2>Setup</h2>",
        f"<p>Every occluder stands on the plane z = 0 (albedo {H.esc(p['support_albedo'])}; occluder albedo "
        f"{H.esc(p['object_albedo'])}), scaled so its largest side is {H.esc(p['size'])} m; the coded-aperture "
        f"mask is a {H.esc(p['size'])} m square of {H.esc(p['mask_cells'])} x {H.esc(p['mask_cells'])} cells "
        f"({H.esc(p['mask_open'])} open) held {H.esc(p['mask_height'])} m above the plane. One "
        f"{H.esc(p['image_size'])} x {H.esc(p['image_size'])} camera at elevation {H.esc(p['elevation_deg'])} deg, "
        f"{H.esc(H.fmt(setup['camera_distance_m']))} m from the origin; envmap {H.esc(p['env_height'])} x "
        f"{H.esc(2 * p['env_height'])}; direct-light transport (K = {H.esc(p['samples'])}).</p>",
        f"<p>Uncertainty: sqrt(diag((A^T A + lr I)^-1)) per texel, radiance per unit pixel noise, with one absolute "
        f"ridge weight lr = {H.esc(H.fmt(setup['lr_absolute']))} for all ({H.esc(p['lr'])} x the unoccluded plane's "
        f"mean squared column norm); its bound, reached by a texel the shadows say nothing about, is "
        f"{H.esc(H.fmt(setup['uncertainty_bound']))}. A texel is resolved below {H.esc(p['threshold'])} x the "
        f"bound. Zenith band: elevation &gt;= {H.esc(p['zenith_deg'])} deg; horizon band: elevation below "
        f"{H.esc(p['horizon_deg'])} deg. Lower is better.</p></section>",
        "<section><h2>Comparison</h2>",
        H.figure(H.read_png(figure_png, 1600), "per occluder: camera view, per-texel uncertainty (one log "
                 "colour scale), per-pixel leverage (one log colour scale)", plot=True,
                 missing="comparison.png missing"),
        H.table(("occluder", *[c for _, c in COLUMNS]), table_rows(results),
                caption="upper-hemisphere uncertainty (lower is better), effective rank (higher is better)"),
        "</section><section><h2>Files</h2><ul>",
    ]
    for name in results["objects"]:
        body.append(f"<li><code>{H.esc(name)}/</code> uncertainty.exr / .png (envmap grid), leverage.exr / .png "
                    "(image)</li>")
    body.append("</ul></section>")
    text = H.page("objcam design: occluder comparison", "".join(body),
                  subtitle=f"{len(results['objects'])} occluders \u00b7 written by <code>objcam design</code>")
    from objcam.image_io import atomic_write_text

    atomic_write_text(path, text)
    return Path(path)
