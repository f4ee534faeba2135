"""How much of the hard suite's error is objcam's model, and how much the photo's silence (issues 22 and 28).

    python -m bench.hard.ceiling [--out /tmp/hard] [--work objcam] [--family lamp] [--write]

For every solved target under ``OUT/captures/*/WORK`` (a run of ``python -m bench.hard``), two measures the suite's
scores alone cannot give:

* **truth fit**: the truth, area-averaged to A's grid, put through objcam's A: its chi-squared per fitted pixel
  value against the target's stated noise (as the solve's verdict computes it) and the median ratio of that
  prediction to the photo over the fitted pixels (1: no bias). Far above 1, the photo holds what A cannot express
  for the true light, e.g. a lamp smaller than a texel, whose shading of the plane depends on where inside the
  texel it sits (A's box texel spreads it over the texel's elevations), or interreflections the transport misses.
* **ceiling** (an inverse crime, on purpose): the target re-made through objcam's own A from the area-averaged
  truth, with zero-mean Gaussian noise at the stated level (seeded per target), solved with default parameters
  and scored by evaluate's metrics beside the row-mean oracle. The model is exact there by construction, so the
  gap between a target's suite score and its ceiling is what model error costs it; a ceiling below the row-mean
  oracle says that even an exact model, with objcam's priors, cannot beat the oracle on that lighting.

This is a diagnostic, not a benchmark of objcam: the suite's own targets never go through objcam's A; these do.
``--write`` puts the block ``bench:hard-ceiling`` into bench/results.md and the rows into
bench/hard_ceiling_rows.json.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import zlib
from pathlib import Path

import numpy as np

from bench.hard.report import _f
from bench.sections import invocation, write_section

TITLE = "Hard cases: model error and the inverse-crime ceiling (issues 22, 28)"
ROWS = Path("bench/hard_ceiling_rows.json")


def truth_fit(pred: np.ndarray, y: np.ndarray, use: np.ndarray, sigma_rel: float) -> dict:
    """{chi2, bias} of a prediction (M, 3) of the photo y (M, 3) over the fitted rows ``use`` (M,) bool: chi-squared
    per pixel value at relative noise ``sigma_rel`` (objcam.solvers.plan.verdict.chi2_per_value's convention) and
    the median over those pixels of predicted / observed luminance (pixels with a positive photo only)."""
    from objcam.solvers.plan.verdict import chi2_per_value

    chi2, _ = chi2_per_value(y[use], pred[use], sigma_rel)
    p, o = pred[use].mean(axis=1), y[use].mean(axis=1)
    pos = o > 0
    return {"chi2": chi2, "bias": float(np.median(p[pos] / o[pos])) if pos.any() else float("nan")}


def crime_photo(pred: np.ndarray, y: np.ndarray, use: np.ndarray, sigma_rel: float, seed: int) -> np.ndarray:
    """(M, 3): ``pred`` (A times the truth) plus zero-mean Gaussian noise of the absolute sigma the real photo y's
    stated relative noise gives (objcam.transport.auto.absolute_noise over its fitted rows ``use``)."""
    from objcam.transport.auto import absolute_noise

    sigma = absolute_noise(y[use], sigma_rel)
    return pred + np.random.default_rng(seed).normal(0.0, sigma, pred.shape)


def _seed(name: str) -> int:
    return zlib.crc32(name.encode())


def _wanted(target: str, families: list[str] | None) -> bool:
    """Whether ``target`` is of one of ``families`` (lighting-name prefixes; None: all)."""
    return not families or any(target.startswith(f + "_") for f in families)


def capture_rows(cap: Path, work: Path, families: list[str] | None = None) -> list[dict]:
    """The rows of one capture's targets (those of ``families``, lighting-name prefixes, or all): truth fit and
    ceiling scores. Reads ``work``'s scene and transport; writes nothing. The ceiling is solved with the default
    SolveParams (the suite's captures set none in capture.toml)."""
    from bench.hard.score import band_energy_ratios
    from objcam.baselines import with_baselines
    from objcam.envmap import read_latlong, resample_to_height
    from objcam.metrics import envmap_metrics
    from objcam.schemas.artifacts import SceneArtifact
    from objcam.solvers.plan.capture import solve_capture
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.rules import fitted_noise
    from objcam.solvers.plan.targets import TargetData
    from objcam.stages.solve import load_targets
    from objcam.truth import truth_envmap_path

    scene = SceneArtifact.load(work / "scene")
    if not any(_wanted(t.name, families) for t in scene.targets):
        return []
    truth_files = {t.name: truth_envmap_path(cap, t.name) for t in scene.targets}
    lost = [name for name, path in truth_files.items() if path is None]
    if lost:  # a later `bench.hard --only` run rewrote the capture for fewer targets than this work folder solved
        print(f"  skipped {cap.name}: no truth for {', '.join(lost)} of {work.name}'s targets (the capture was "
              f"rewritten since, e.g. by `bench.hard --only`): rerun `python -m bench.hard --out {cap.parent.parent}`",
              file=sys.stderr)
        return []
    data = load_targets(scene, work / "transport")
    rows, truths = {}, {}
    for t in scene.targets:
        d = data[t.name]
        tr = d.transport
        truth = resample_to_height(read_latlong(truth_files[t.name])[..., :3].astype(np.float64), tr.output_height)
        if tr.output_height != tr.env_height:
            raise ValueError(f"{work}: a supersampled A (env_height {tr.env_height}): run on a default work folder")
        truths[t.name] = truth
        sigma_rel, _ = fitted_noise(t, d.pooled, d.pooled_ok, tr.downsample)
        pred = tr.predict_pixels(tr.x_from_envmap(truth)).astype(np.float64)
        fit = truth_fit(pred, d.y, d.use, sigma_rel)
        rows[t.name] = {"target": t.name, "capture": cap.name, "noise_sigma": sigma_rel,
                        "truth_chi2": fit["chi2"], "truth_bias": fit["bias"]}
        # every target is re-made (the joint plan may couple them), only the families asked for are scored
        data[t.name] = TargetData(tr, d.pooled, d.pooled_ok, crime_photo(pred, d.y, d.use, sigma_rel,
                                                                         _seed(t.name)), d.use)
    sols = solve_capture(scene, data, SolveParams(), cap)
    out = []
    for name, row in rows.items():
        if not _wanted(name, families):
            continue
        s = sols[name]
        m = with_baselines(envmap_metrics(s.envmap, truths[name], s.mask), truths[name], s.mask)
        row.update({"ceiling_ssim": m["ssim"], "ceiling_tonemapped_rmse": m["tonemapped_rmse"],
                    "ceiling_brightest_angle_deg": m["brightest_angle_deg"],
                    "ceiling_band_energy": band_energy_ratios(s.envmap, truths[name]),
                    "row_mean_ssim": m["baselines"]["row_mean"]["ssim"],
                    "ceiling_beats_row_mean": m["beats_row_mean"]})
        out.append(row)
    return out


def _spread(vals, fmt: str = ".3g") -> str:
    """``median (min-max)`` of ``vals``."""
    v = np.asarray(vals, float)
    return f"{np.median(v):{fmt}} ({v.min():{fmt}}-{v.max():{fmt}})" if v.size else ""


@functools.cache
def _families() -> dict[str, str]:
    from bench.hard.design import cases

    return {c.light.name: c.light.family for c in cases()}


def family_of(target: str) -> str:
    """The lighting family of a suite target name (``lamp30_r0_n2`` -> lamp), as bench.hard.report groups them."""
    name = target.split("_r")[0]
    return _families().get(name, name)


def ceiling_targets(rows: list[dict], suite: dict[str, dict]) -> list[str]:
    """bench.hard.report.targets' met / missed lines for the ceiling's scores (the truth's source contrast from
    the suite's rows; targets the suite did not solve are left out)."""
    from bench.hard.report import targets

    pseudo = []
    for r in rows:
        base = suite.get(r["target"])
        if not base or base.get("status") != "ok":
            continue
        pseudo.append({"target": r["target"], "status": "ok", "noise": base["noise"], "ssim": r["ceiling_ssim"],
                       "band_energy": r["ceiling_band_energy"], "source_contrast": base["source_contrast"],
                       "brightest_angle_deg": r["ceiling_brightest_angle_deg"],
                       "beats_row_mean": r["ceiling_beats_row_mean"], "verdict": {}})
    return [ln for ln in targets(pseudo) if "verdict" not in ln]


def markdown(rows: list[dict], suite: dict[str, dict], header: list[str]) -> str:
    """The block: one line per lighting family and noise level (median and range), then the counts."""
    lines = header + [
        "",
        "| family | noise | targets | suite SSIM median | ceiling SSIM median | row-mean SSIM median | truth chi2 "
        "median (range) | truth bias median (range) | beat row-mean: suite / ceiling |",
        "|---|---:|---:|---:|---:|---:|---|---|---|",
    ]
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((family_of(r["target"]), r["target"].rsplit("_n", 1)[1]), []).append(r)
    for (fam, noise), rs in sorted(groups.items()):
        real = [suite[r["target"]] for r in rs if suite.get(r["target"], {}).get("ssim") is not None]
        lines.append(
            f"| {fam} | {noise}% | {len(rs)} | {_f(np.median([s['ssim'] for s in real]) if real else None)} | "
            f"{_f(np.median([r['ceiling_ssim'] for r in rs]))} | {_f(np.median([r['row_mean_ssim'] for r in rs]))}"
            f" | {_spread([r['truth_chi2'] for r in rs])} | {_spread([r['truth_bias'] for r in rs], '.3f')} | "
            f"{sum(bool(s.get('beats_row_mean', {}).get('ssim')) for s in real)} / "
            f"{sum(bool(r['ceiling_beats_row_mean']['ssim']) for r in rs)} |")
    n = len(rows)
    real_beats = sum(bool(suite.get(r["target"], {}).get("beats_row_mean", {}).get("ssim")) for r in rows)
    ceil_beats = sum(bool(r["ceiling_beats_row_mean"]["ssim"]) for r in rows)
    lines += ["", "Issue 22's targets (and issue 28's row-mean share) if objcam's model were exact (the ceiling's "
              "solves, scored as the suite's block scores objcam's; the verdict is the suite's, not repeated here):",
              ""] + ceiling_targets(rows, suite)
    lines += ["", f"- beat the row-mean oracle in SSIM: the suite's solves {real_beats} of {n}, the ceiling "
              f"{ceil_beats} of {n} ({ceil_beats / max(n, 1):.0%})",
              f"- truth chi2 above 4 (the verdict's yellow line): {sum(r['truth_chi2'] > 4 for r in rows)} of {n}; "
              f"truth bias outside [0.99, 1.01]: {sum(abs(r['truth_bias'] - 1) > 0.01 for r in rows)} of {n}"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench/out/hard"), help="the suite's --out")
    ap.add_argument("--work", default="objcam", help="the work folder inside each capture (default settings)")
    ap.add_argument("--family", default="", help="comma-separated lighting-name prefixes (default: all)")
    ap.add_argument("--suite-rows", type=Path, default=Path("bench/hard_rows.json"),
                    help="the suite's rows, for its SSIM beside the ceiling")
    ap.add_argument("--write", action="store_true", help="write the block and bench/hard_ceiling_rows.json")
    a = ap.parse_args(argv)
    families = [f for f in a.family.split(",") if f] or None
    if not (a.out / "captures").is_dir():
        print(f"error: {a.out / 'captures'} does not exist: run the suite first (`make bench BENCH=hard`, or "
              f"`python -m bench.hard --out {a.out}`), or pass --out its folder", file=sys.stderr)
        return 2
    rows = []
    for cap in sorted((a.out / "captures").iterdir()):
        work = cap / a.work
        if not (work / "solve").is_dir():
            continue
        got = capture_rows(cap, work, families)
        for r in got:
            print(f"  {r['target']:<22} truth chi2 {r['truth_chi2']:8.2f}  bias {r['truth_bias']:.4f}  ceiling SSIM "
                  f"{r['ceiling_ssim']:.3f} (row-mean {r['row_mean_ssim']:.3f})", flush=True)
        rows += got
    suite = {}
    if a.suite_rows.is_file():
        suite = {r["target"]: r for r in json.loads(a.suite_rows.read_text())["rows"]}
    header = [invocation("bench.hard.ceiling", argv) + f": {len(rows)} targets of the suite's run in {a.out}, "
              f"work folder {a.work}; the suite's SSIM from {a.suite_rows}."]
    text = markdown(rows, suite, header)
    print(text)
    if a.write:
        write_section("hard-ceiling", text, TITLE)
        ROWS.write_text(json.dumps({"made_by": header[0], "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
