"""Joint solve ablation (issue 6): a table shaped like the method's Table 1, on objcam's scenes.

(a) unknown albedo: the bunny on a 'dots' support whose albedo is not given, 3 targets = the forest HDRI rotated by
    0/120/240 degrees, one 128 x 128 camera, 32 x 64 envmap, targets path-traced with GI (512 spp, max depth 6)
    plus camera noise; A by transport model=auto (direct + indirect).
(b) known albedo: the bench capture's forest target (bench/run.py: 2048 spp, 0.1% noise), A by model=auto.

Rows: plain least squares (x >= 0, no regularisation), + L2, + L2 + smoothness (the default weights),
+ automatic regularisation (GCV), the paper's damped method, Adam through Mitsuba at equal wall time (A + solve of
the default row), Adam for a long budget ("to convergence", capped). Columns: envmap relative RMSE and SSIM
(after the best-fit scale per channel when the albedo is unknown), albedo relative RMSE and SSIM, time (A + solve).
Then, per bundled HDRI of the bench capture (known albedo), the relative RMSE of the GCV choice against the best
hand-tuned ls on a grid.

    python -m bench.ablation [--quick] [--adam-long-seconds 600]

Prints markdown; ``--write`` appends it to bench/results.md under "## Joint solve ablation (issue 6)".
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

OUT = Path("bench/out/ablation")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def load() -> str:
    return f"{os.getloadavg()[0]:.1f}"


def unknown_scene(quick: bool) -> Path:
    from objcam.synth import SynthParams, synthesize

    size, spp = (64, 128) if quick else (128, 512)
    cap = OUT / f"dots-forest-3rot-{size}px-{spp}spp"
    if not (cap / "capture.toml").is_file():
        shutil.rmtree(cap, ignore_errors=True)
        synthesize(cap, SynthParams(envmap="forest", rotations_deg=[0.0, 120.0, 240.0], support_albedo="dots",
                                    support_albedo_known=False, cameras=[{"width": size, "height": size}], spp=spp))
    return cap


def known_scene(hdris: tuple[str, ...], quick: bool, single: str | None = None) -> Path:
    """The bench capture (bench/run.py; rendered if missing), or a copy holding only target ``single``."""
    from bench.run import synth_targets

    spp, size = (256, 64) if quick else (2048, 128)
    base = synth_targets(Path("bench/out") if not quick else OUT / "quick", hdris, spp, size, 1e-3)
    if single is None:
        return base
    cap = OUT / f"known-{single}-{size}px"
    if not (cap / "capture.toml").is_file():
        shutil.rmtree(cap, ignore_errors=True)
        (cap / "targets").mkdir(parents=True)
        (cap / "truth").mkdir()
        shutil.copy(base / "object.ply", cap / "object.ply")
        for ext in ("exr", "json"):
            shutil.copy(base / "targets" / f"{single}.{ext}", cap / "targets" / f"{single}.{ext}")
        shutil.copy(base / "truth" / f"{single}.exr", cap / "truth" / f"{single}.exr")
        toml = (base / "capture.toml").read_text()
        head, targets = toml.split("[[targets]]", 1)
        block = next(b for b in toml.split("[[targets]]")[1:] if f'name = "{single}"' in b)
        (cap / "capture.toml").write_text(head + "[[targets]]" + block)
        (cap / "truth" / "truth.json").write_text(json.dumps({"envmaps": {single: f"truth/{single}.exr"}}))
    return cap


def run_row(cap: Path, sets: list[str]) -> dict:
    """Run solve + evaluate with ``sets`` (the transport is cached in the capture); mean metrics and times."""
    from objcam.pipeline.cli import main

    args = ["run", str(cap), "--quiet", "--until", "evaluate", "--set", "transport.model=auto"]
    for s in sets:
        args += ["--set", s]
    ld = load()
    if main(args) != 0:
        raise RuntimeError(f"pipeline failed for {sets}")
    log(f"    done ({load()})")
    w = cap / "objcam"
    stage = lambda n: json.loads((w / n / "stage.json").read_text())  # noqa: E731
    metrics = json.loads((w / "evaluate" / "metrics.json").read_text())
    mean = lambda k: (sum(v[k] for v in metrics.values()) / len(metrics)) if all(  # noqa: E731
        v.get(k) is not None for v in metrics.values()) else None
    return {"env_rmse": mean("relative_rmse"), "env_ssim": mean("ssim"), "alb_rmse": mean("albedo_relative_rmse"),
            "alb_ssim": mean("albedo_ssim"), "a_s": stage("transport")["wall_seconds"],
            "solve_s": stage("solve")["wall_seconds"], "load": ld,
            "solve": next(iter(json.loads((w / "solve" / "stage.json").read_text())["metrics"]["targets"].values()))}


def table(cap: Path, adam_long: float, label: str) -> list[str]:
    # without a prior the alternation crawls (hundreds of sweeps at 3 Gram matrices each): capped at 15 sweeps
    rows = [("plain least squares (x >= 0), 15 sweeps", ["solve.ls=0", "solve.lr=0", "solve.max_iter=15"]),
            ("+ L2, 15 sweeps", ["solve.ls=0", "solve.lr=1e-3", "solve.max_iter=15"]),
            ("+ L2 + smoothness (default)", []),
            ("+ automatic regularisation (GCV)", ["solve.auto_reg=gcv"]),
            ("paper's damped method", ["solve.method=paper"])]
    res = {}
    for name, sets in rows:
        log(f"  {label}: {name}")
        res[name] = run_row(cap, sets)
    ours = res["+ L2 + smoothness (default)"]
    eq = ours["a_s"] + ours["solve_s"]
    log(f"  {label}: adam, equal time {eq:.0f} s")
    res[f"Adam, equal time ({eq:.0f} s)"] = run_row(cap, ["solve.method=adam", f"solve.adam_seconds={eq:.1f}",
                                                         "solve.adam_max_iter=100000"])
    log(f"  {label}: adam, long {adam_long:.0f} s")
    res[f"Adam, long (<= {adam_long:.0f} s)"] = run_row(cap, ["solve.method=adam", f"solve.adam_seconds={adam_long}",
                                                             "solve.adam_max_iter=100000"])
    f3 = lambda v: "" if v is None else f"{v:.3f}"  # noqa: E731
    out = [f"| {label} | envmap rel. RMSE | envmap SSIM | albedo rel. RMSE | albedo SSIM | time: A + solve (s) "
           "| load | notes |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for name, r in res.items():
        s = r["solve"]
        note = s.get("stopped") and f"{s['iterations']} it., {s['stopped']}" or (
            f"{s.get('iterations')} sweeps" + (f", ls {s['auto_reg']['ls_relative']:.1e}" if s.get("auto_reg") else ""))
        a_s = 0.0 if s.get("method") == "adam" else r["a_s"]
        out.append(f"| {name} | {f3(r['env_rmse'])} | {f3(r['env_ssim'])} | {f3(r['alb_rmse'])} | {f3(r['alb_ssim'])} "
                   f"| {a_s:.1f} + {r['solve_s']:.1f} | {r['load']} | {note} |")
    return out


def autoreg_check(cap: Path, grid: list[float]) -> list[str]:
    """Known albedo, every HDRI: relative RMSE at each hand-tuned ls and with GCV."""
    per: dict[str, dict[str, float]] = {}
    for ls in grid:
        log(f"  ls = {ls:g}")
        run_row(cap, [f"solve.ls={ls}"])
        m = json.loads((cap / "objcam" / "evaluate" / "metrics.json").read_text())
        for t, v in m.items():
            per.setdefault(t, {})[f"{ls:g}"] = v["relative_rmse"]
    run_row(cap, ["solve.auto_reg=gcv"])
    m = json.loads((cap / "objcam" / "evaluate" / "metrics.json").read_text())
    s = json.loads((cap / "objcam" / "solve" / "stage.json").read_text())["metrics"]["targets"]
    out = ["| HDRI | best hand-tuned ls | its rel. RMSE | GCV ls | GCV rel. RMSE | GCV / best |",
           "|---|---:|---:|---:|---:|---:|"]
    for t, v in per.items():
        best = min(v, key=v.get)
        g = m[t]["relative_rmse"]
        out.append(f"| {t} | {best} | {v[best]:.3f} | {s[t]['auto_reg']['ls_relative']:.1e} | {g:.3f} | "
                   f"{g / v[best]:.3f} |")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="64 px, fewer spp, short Adam (a smoke run)")
    ap.add_argument("--adam-long-seconds", type=float, default=None)
    ap.add_argument("--write", action="store_true", help="append the tables to bench/results.md")
    ap.add_argument("--parts", default="abc", help="a: unknown albedo table, b: known albedo, c: GCV per HDRI")
    a = ap.parse_args(argv)
    adam_long = a.adam_long_seconds or (60.0 if a.quick else 600.0)
    hdris = ("forest", "courtyard", "city", "sunrise")
    t0 = time.perf_counter()
    ta = tb = tc = []
    if "a" in a.parts:
        log("(a) unknown albedo, 3 illuminations")
        ta = table(unknown_scene(a.quick), adam_long, "(a) dots, 3 rotations")
    if "b" in a.parts:
        log("(b) known albedo, forest")
        tb = table(known_scene(hdris, a.quick, "forest"), adam_long, "(b) known albedo, forest")
    if "c" in a.parts:
        log("auto regularisation per HDRI")
        tc = autoreg_check(known_scene(hdris, a.quick), [1e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0])
    md = "\n".join(ta + [""] + tb + [""] + tc)
    print(md)
    log(f"ablation done in {time.perf_counter() - t0:.0f} s")
    if a.write:
        with open("bench/results.md", "a") as fh:
            fh.write("\n## Joint solve ablation (issue 6)\n\n" + md + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
