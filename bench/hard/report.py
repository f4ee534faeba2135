"""The hard-case suite's block of bench/results.md: issue 22's targets met or missed, summaries per noise level and
per lighting family (median, worst, spread), which cases beat the row-mean oracle, and one row per target."""

from __future__ import annotations

import numpy as np

from bench.hard.score import BANDS

FAMILIES = ("lamp", "room", "window", "sun", "overcast", "hdri")


def _f(v, fmt=".3f") -> str:
    return "" if v is None else format(v, fmt)


def _ratio(v) -> str:
    """A ratio over a baseline: the baseline's error can be ~0 (a room whose tonemapped truth is its row means)."""
    return "" if v is None else (f"{v:.2f}" if v < 100 else f"{v:.1g}")


def factor_table(rows: list[dict], noises) -> list[str]:
    """Median SSIM (and how many solved) per level of each geometry factor, per noise level: which factor hurts."""
    lines = ["| factor | level | " + " | ".join(f"SSIM median at {100 * n:g}% (solved)" for n in noises) + " |",
             "|---|---|" + "---:|" * len(noises)]
    for factor, key in (("object", "object"), ("camera elevation", "elevation_deg"), ("albedo", "albedo")):
        for level in sorted({r[key] for r in rows}, key=str):
            cells = []
            for n in noises:
                s = [r["ssim"] for r in _solved(rows, n) if r[key] == level]
                tot = sum(r[key] == level and r["noise"] == n for r in rows)
                cells.append(f"{np.median(s):.3f} ({len(s)}/{tot})" if s else f"- (0/{tot})")
            lines.append(f"| {factor} | {level:g} |" if isinstance(level, float) else f"| {factor} | {level} |")
            lines[-1] += " " + " | ".join(cells) + " |"
    return lines


def _inf(v) -> float:
    return float("inf") if v is None else float(v)  # JSON's null for an infinite ratio


def _solved(rows, noise=None):
    return [r for r in rows if r["status"] == "ok" and (noise is None or r["noise"] == noise)]


#: a target whose truth's constant map (its mean per channel) scores at least this SSIM: the tonemapped truth is
#: flat over nearly all the sky, so SSIM cannot tell a map from a flat one; reported beside the verdict line. (Until
#: session 42 the dark rooms were such targets: their 99th percentile was the walls' uniform value, now the
#: tonemap's white there is the brightest lamp, objcam.metrics.PLATEAU_SHARE; kept as a guard.)
SSIM_BLIND = 0.99


def _baseline_ssim(r: dict, name: str) -> float:
    """The SSIM of the baseline ``name`` (constant, row_mean) in row ``r``; 0 where it was not scored."""
    return (r.get("baselines") or {}).get(name, {}).get("ssim", 0.0)


def _ssim_blind(r: dict) -> bool:
    return _baseline_ssim(r, "constant") >= SSIM_BLIND


#: a target whose row-mean map scores SSIM 1 to this tolerance: no map scores more than it (a tie is not a win):
#: reported beside the beats-row-mean line as what that share can reach (the dark rooms until session 42, see
#: SSIM_BLIND; kept as a guard)
ROW_MEAN_PERFECT = 1e-9


def _row_mean_perfect(r: dict) -> bool:
    return _baseline_ssim(r, "row_mean") >= 1.0 - ROW_MEAN_PERFECT


def _band_ok(r, lo, hi) -> bool:
    return all(b is not None and lo <= b <= hi for b in r["band_energy"])


def targets(rows: list[dict]) -> list[str]:
    """Markdown lines: each target of issue 22 (and issue 28's >= 80% beating the row-mean oracle), met or
    missed on the solved targets, and how many targets were not solved (refused or failed) and so not measured."""
    out = []
    unsolved = [r for r in rows if r["status"] != "ok"]

    def line(ok, text):
        out.append(f"- {'met' if ok else '**missed**'}: {text}")

    for noise, med_t, worst_t in ((0.02, 0.70, 0.45), (0.005, 0.78, None)):
        s = [r["ssim"] for r in _solved(rows, noise)]
        n_un = sum(r["noise"] == noise for r in unsolved)
        tail = f" ({len(s)} solved" + (f", {n_un} not solved: not measured" if n_un else "") + ")"
        if not s:
            out.append(f"- **not measured**: SSIM at {100 * noise:g}% noise: no target solved{tail}")
            continue
        med, worst = float(np.median(s)), float(np.min(s))
        ok = med >= med_t and (worst_t is None or worst >= worst_t) and not n_un
        line(ok, f"SSIM at {100 * noise:g}% noise: median {med:.3f} (>= {med_t})"
             + (f", worst {worst:.3f} (>= {worst_t})" if worst_t else "") + tail)
    s = _solved(rows)
    if s:
        f90 = np.mean([_band_ok(r, 0.67, 1.5) for r in s])
        all2 = np.mean([_band_ok(r, 0.5, 2.0) for r in s])
        line(f90 >= 0.9, f"every elevation band within [0.67, 1.5] of the truth's energy in >= 90% of targets: "
             f"{100 * f90:.0f}%")
        line(all2 == 1.0, f"every band within [0.5, 2] in all targets: {100 * all2:.0f}%")
        peaked = [r for r in s if r["source_contrast"] >= 3 and r["brightest_angle_deg"] is not None]
        if peaked:
            within = np.mean([r["brightest_angle_deg"] <= 5.6 for r in peaked])
            line(within >= 0.95, f"brightest source within 5.6 deg in >= 95% of the {len(peaked)} targets whose "
                 f"brightest source is >= 3x the next: {100 * within:.0f}%")
        b_s = np.mean([r["beats_row_mean"]["ssim"] for r in s])
        b_t = np.mean([r["beats_row_mean"]["tonemapped_rmse"] for r in s])
        perfect = [r["target"] for r in s if _row_mean_perfect(r)]
        # issue 28 counts the cases that beat the oracle "in SSIM and in tonemapped RMSE": both shares must reach it
        line(b_s >= 0.8 and b_t >= 0.8, f"beats the row-mean oracle in >= 80% of targets in SSIM and in tonemapped "
             f"RMSE (issue 28): {100 * b_s:.0f}% and {100 * b_t:.0f}%"
             + (f"; in {len(perfect)} the row-mean map scores SSIM 1 (the tonemapped truth white over the whole "
                f"sky: no map can beat it, so at most {100 * (len(s) - len(perfect)) / len(s):.0f}%): "
                f"{', '.join(perfect)}" if perfect else ""))
        graded = [r for r in s if (r.get("verdict") or {}).get("grade")]
        if graded:
            low = [r for r in graded if r["ssim"] < 0.4]
            high = [r for r in graded if r["ssim"] >= 0.7]
            low_red = sum(r["verdict"]["grade"] == "red" for r in low)
            high_red = [r["target"] for r in high if r["verdict"]["grade"] == "red"]
            line(low_red == len(low), f"the verdict: every target with SSIM < 0.4 graded red: {low_red} of "
                 f"{len(low)}" + (f" (not red: {', '.join(r['target'] for r in low if r['verdict']['grade'] != 'red')})"
                                  if low_red < len(low) else ""))
            blind = {r["target"] for r in high if _ssim_blind(r)}
            blind_red = sorted(blind.intersection(high_red))
            line(not high_red, f"no target with SSIM >= 0.7 graded red: {len(high_red)} of {len(high)}"
                 + (f" ({', '.join(high_red)})" if high_red else "")
                 + (f"; of them {len(blind_red)} where SSIM cannot tell a map from a flat one (the truth's constant "
                    f"map scores >= {SSIM_BLIND}: {', '.join(blind_red)}), so {len(high_red) - len(blind_red)} of "
                    f"{len(high) - len(blind)} otherwise" if blind_red else ""))
    if unsolved:
        for kind in sorted({r["status"] for r in unsolved}):
            k = [r for r in unsolved if r["status"] == kind]
            out.append(f"- {len(k)} of {len(rows)} targets {kind}: "
                       + "; ".join(sorted({r.get('error', '')[:160] for r in k}))
                       + (f" ({', '.join(r['target'] for r in k)})" if len(k) <= 12 else ""))
    return out


def _stats(vals) -> str:
    if not vals:
        return "| | | |"
    v = np.asarray(vals, float)
    return f"| {np.median(v):.3f} | {v.min():.3f} | {np.percentile(v, 25):.2f}-{np.percentile(v, 75):.2f} |"


def summary_table(rows: list[dict], noises) -> list[str]:
    lines = ["| family | noise | solved / all | SSIM median | worst | IQR | masked SSIM median | row-mean SSIM "
             "median | SSIM skill median | tm RMSE / row-mean median | beats row-mean (SSIM, tm RMSE) |",
             "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---|"]
    for fam in (*FAMILIES, "all"):
        for noise in noises:
            allr = [r for r in rows if r["noise"] == noise and (fam == "all" or r["family"] == fam)]
            s = _solved(allr)
            if not allr:
                continue
            label = f"**{fam}**" if fam == "all" else fam
            if not s:
                lines.append(f"| {label} | {100 * noise:g}% | 0 / {len(allr)} | | | | | | | | |")
                continue
            lines.append(
                f"| {label} | {100 * noise:g}% | {len(s)} / {len(allr)} " + _stats([r["ssim"] for r in s])
                + f" {np.median([r['ssim_masked'] for r in s]):.3f} "
                f"| {np.median([r['baselines']['row_mean']['ssim'] for r in s]):.3f} "
                f"| {np.median([r['skill']['ssim_over_row_mean'] for r in s]):+.3f} "
                f"| {_ratio(np.median([_inf(r['skill']['tonemapped_rmse_over_row_mean']) for r in s]))} "
                f"| {sum(r['beats_row_mean']['ssim'] for r in s)}, "
                f"{sum(r['beats_row_mean']['tonemapped_rmse'] for r in s)} of {len(s)} |")
    return lines


def case_table(rows: list[dict]) -> list[str]:
    bands = " / ".join(f"{lo:g}-{hi:g}" for lo, hi in BANDS)
    lines = ["| target | object, camera el., albedo | noise (all) | status | SSIM | masked | const. SSIM | "
             "row-mean SSIM | tm RMSE | / row-mean | rel. RMSE | band energy " + bands + " | below horizon | "
             "brightest (deg) | contrast | A (s) | solve (s) | verdict |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        geo = f"{r['object']}, {r['elevation_deg']:g}, {r['albedo']} | {100 * r['noise_sigma']:.2g}%"
        if r["status"] != "ok":
            why = f" ({r['negative_pixels']} px < 0, min {r['min']:.2g})" if r["negative_pixels"] else ""
            lines.append(f"| {r['target']} | {geo} | {r['status']}{why} |" + " |" * 14)
            continue
        b = r["baselines"]
        lines.append(
            f"| {r['target']} | {geo} | ok | {r['ssim']:.3f} | {r['ssim_masked']:.3f} | {b['constant']['ssim']:.3f} "
            f"| {b['row_mean']['ssim']:.3f} | {r['tonemapped_rmse']:.3f} "
            f"| {_ratio(r['skill']['tonemapped_rmse_over_row_mean'])} | {r['relative_rmse']:.2f} "
            f"| {' / '.join(_f(x, '.2f') for x in r['band_energy'])} | {_f(r.get('below_horizon_energy'), '.2f')} "
            f"| {_f(r['brightest_angle_deg'], '.1f')} "
            f"| {min(r['source_contrast'], 1e6):.3g} | {r['a_seconds']:.1f}{'*' if r.get('a_cached') else ''} "
            f"| {_f(r['solve_seconds'], '.2f')}{'*' if r.get('solve_cached') else ''} "
            f"| {_verdict_cell(r)} |")
    return lines


def _verdict_cell(r: dict) -> str:
    """The solve's grade, with chi-squared and the share of sky not determined (objcam.solvers.plan.verdict)."""
    v = r.get("verdict") or {}
    if not v.get("grade"):
        return ""
    return (f"{v['grade']} (chi2 {_f(v.get('chi2'), '.1f')}, undetermined {_f(v.get('uncertain_area'), '.2f')}, "
            f"{'A: ' + str(r.get('transport_model')) if r.get('transport_model') else ''})")


def markdown(rows: list[dict], header: list[str], noises) -> str:
    s = _solved(rows)
    beat_s = [r["target"] for r in s if r["beats_row_mean"]["ssim"]]
    beat_t = [r["target"] for r in s if r["beats_row_mean"]["tonemapped_rmse"]]
    lines = [*header, "", "Issue 22's targets (and issue 28's) in this run:", "", *targets(rows), "",
             "### Per lighting family and noise level", "",
             "SSIM as evaluate reports it (tonemapped, unsolved texels zeroed in both maps; `masked` ignores them "
             "instead); row-mean = the truth's per-row mean over the solved texels, an oracle that knows every "
             "elevation's brightness and nothing about azimuth; skill = SSIM minus the row-mean map's; tm RMSE / "
             "row-mean < 1 is better than the oracle. IQR: 25th-75th percentile.", "",
             *summary_table(rows, noises), "",
             "By geometry factor (each factor's levels meet every lighting family, bench/hard/design.py):", "",
             *factor_table(rows, noises), "",
             f"Beat the row-mean oracle in SSIM ({len(beat_s)} of {len(s)} solved): "
             + (", ".join(beat_s) or "none") + ".", "",
             f"Beat it in tonemapped RMSE ({len(beat_t)} of {len(s)}): " + (", ".join(beat_t) or "none") + ".", "",
             "### Every target", "",
             "Band energy: estimate / truth solid-angle luminance energy per elevation band above the horizon "
             "(degrees); below horizon: the estimate's energy in the rows below the horizon over the truth's above "
             "it (light put where the plane hides the sky). Noise (all): capture.toml's noise_sigma, hypot(the added "
             "noise, the render's own Monte Carlo noise at the median pixel, bench.hard.scene.median_pixel_noise), "
             "both relative to the median pixel. Contrast: the truth's "
             "brightest source's peak over the next one's. A (s): the transport stage's wall time, one A per "
             "geometry (shared by its targets); * marks a time read from a stage "
             "objcam took from its cache (an earlier run's). Verdict: the solve's own grade from the data alone "
             "(objcam.solvers.plan.verdict), its chi-squared against the noise, the share of the sky its "
             "uncertainty exceeds, and the transport model `auto` chose.", "",
             *case_table(rows)]
    return "\n".join(lines) + "\n"
