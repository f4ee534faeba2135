"""The transport on a Dask cluster against in-process (issue 25): CPU overhead of the distributed path on the demo
capture, and a projection to more workers from the per-shard timings measured here.

    python -m bench.cluster_bench [--workers 2] [--env-height 32] [--project 8] [--extrapolate 64] [--write]

Builds the demo capture's transport (the default settings, ``transport.env_height`` as given) once in this
process and once on a LocalCluster of ``--workers`` single-thread workers, and reports:

- CPU seconds (user + system) of every process involved: this one (the driver, which also hosts the scheduler)
  and every worker and nanny process (psutil, summed over the process tree), for the cluster's start and for
  the transport on the started cluster; the overhead is the cluster's transport CPU over the in-process CPU;
- A's and the Gram matrix's largest difference from the in-process ones;
- the projected wall time on ``--project`` workers: the driver's own work (its wall time minus the time it waited
  for shards) plus, per phase (direct blocks, gather chunks, Gram blocks), the longest-processing-time-first
  schedule of the measured shard times (Dask's task stream) on that many workers.

With ``--write`` the table goes to bench/results.md's ``cluster`` block. Timings on a machine shared with other
work are inflated; the load average is printed beside them.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

import numpy as np

OUT = Path("bench/out/cluster")


def _tree_cpu() -> float:
    """CPU seconds (user + system) of this process and every live descendant."""
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.NoSuchProcess:
            pass
    return total


def _capture() -> Path:
    from objcam.pipeline.cli import main

    cap = OUT / "capture"
    if not (cap / "capture.toml").is_file():
        shutil.rmtree(cap, ignore_errors=True)
        assert main(["synth", str(cap), "--object", "bunny", "--envmap", "forest"]) == 0  # make demo's capture
    assert main(["run", str(cap), "--until", "scene", "-q"]) == 0
    return cap


def _build(cap: Path, out: Path, env_height: int) -> tuple[dict, float, float]:
    """The transport stage into ``out``; returns (metrics, wall seconds, CPU seconds of the process tree)."""
    from objcam.pipeline.stage import StageInputs
    from objcam.stages import transport as stage

    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    c0, t0 = _tree_cpu(), time.perf_counter()
    m = stage.run(StageInputs(capture=cap, upstream={"scene": cap / "objcam" / "scene"}, out=out, quiet=True),
                  stage.Params(env_height=env_height)).metrics
    return m, time.perf_counter() - t0, _tree_cpu() - c0


def _lpt(times: list[float], workers: int) -> float:
    """Makespan of the longest-processing-time-first schedule of ``times`` on ``workers``."""
    load = [0.0] * workers
    for t in sorted(times, reverse=True):
        load[load.index(min(load))] += t
    return max(load)


def _phase_times(stream: list[dict]) -> dict[str, list[float]]:
    """Compute seconds of each objcam shard in Dask's task stream, by phase (direct, gather, gram)."""
    out: dict[str, list[float]] = {}
    for rec in stream:
        key = str(rec.get("key", ""))
        if not key.startswith("objcam-"):
            continue
        phase = key.split("-")[1]
        secs = sum(s["stop"] - s["start"] for s in rec.get("startstops", []) if s.get("action") == "compute")
        out.setdefault(phase, []).append(secs)
    return out


def measure(workers: int, env_height: int) -> dict:
    """Build the demo's transport in-process and on a LocalCluster of ``workers``; the raw numbers."""
    import zarr
    from distributed import get_task_stream

    from objcam.pipeline.cluster import connect
    from objcam.transport.engine import using
    from objcam.transport.shards import DaskEngine

    os.environ["OBJCAM_QUIET"] = "1"
    cap = _capture()
    load0 = os.getloadavg()[0]
    m_in, wall_in, cpu_in = _build(cap, OUT / "inprocess", env_height)
    c0 = _tree_cpu()
    with connect(f"local:{workers}") as client:
        client.wait_for_workers(workers)
        start_cpu = _tree_cpu() - c0
        with using(DaskEngine(client)), get_task_stream(client) as ts:
            m_d, wall_d, cpu_d = _build(cap, OUT / "dask", env_height)
        stream = ts.data
    a = np.asarray(zarr.open_group(str(OUT / "inprocess" / "cam0"), mode="r")["A"][...])
    b = np.asarray(zarr.open_group(str(OUT / "dask" / "cam0"), mode="r")["A"][...])
    ga, gb = np.load(OUT / "inprocess" / "cam0" / "gram.npy"), np.load(OUT / "dask" / "cam0" / "gram.npy")
    return {"workers": workers, "env_height": env_height, "m_in": m_in, "wall_in": wall_in, "cpu_in": cpu_in,
            "m_d": m_d, "wall_d": wall_d, "cpu_d": cpu_d, "start_cpu": start_cpu, "phases": _phase_times(stream),
            "max_rel_A": float(np.abs(a - b).max() / np.abs(a).max()) if a.shape == b.shape else float("nan"),
            "max_rel_gram": float(np.abs(ga - gb).max() / np.abs(ga).max()), "load": (load0, os.getloadavg()[0])}


def summarize(raw: dict, project: list[int], extrapolate: int | None = None) -> dict:
    """A table row from ``measure``'s numbers; with ``extrapolate`` (an env_height) the per-shard times scaled to
    that many texels: columns x r (r: the texel ratio), the Gram's block products x r^2; the driver's own work
    (samples, auto's sampled renders, the gather's rays) does not depend on the texel count."""
    m_in, m_d, phases, wall_in = raw["m_in"], raw["m_d"], raw["phases"], raw["wall_in"]
    shape = f"{m_in['pixels_kept']:,} x {m_in['texels_kept']:,}"
    if extrapolate:
        r = (extrapolate / raw["env_height"]) ** 2
        phases = {k: [t * (r * r if k == "gram" else r) for t in v] for k, v in phases.items()}
        lap = {k[len("cpu_seconds_"):]: v for k, v in m_in.items() if k.startswith("cpu_seconds_") and k != "cpu_seconds"}
        scaled = sum(v * (r if k in ("direct", "gather_columns") else 1.0) for k, v in lap.items())
        scaled += m_in["gram_seconds"] * r * r
        wall_in = scaled * raw["wall_in"] / max(sum(lap.values()) + m_in["gram_seconds"], 1e-9)
        shape = f"~{m_in['pixels_kept']:,} x {int(m_in['texels_kept'] * r):,} (extrapolated from {shape})"
    driver = raw["wall_d"] - m_d["engine_driver_wait_seconds"]  # what the driver does itself
    return {"workers": raw["workers"], "shape": shape, "model": m_in["model"], "wall_in": wall_in,
            "cpu_in": raw["cpu_in"], "wall_d": raw["wall_d"], "cpu_d": raw["cpu_d"], "start_cpu": raw["start_cpu"],
            "driver": driver, "shards": {k: (len(v), sum(v)) for k, v in phases.items()},
            "proj": {w: driver + sum(_lpt(t, w) for t in phases.values()) for w in project},
            "shard_cpu": {k[len("engine_cpu_"):-len("_seconds")]: v for k, v in m_d.items()
                          if k.startswith("engine_cpu_")},
            "max_rel_A": raw["max_rel_A"], "max_rel_gram": raw["max_rel_gram"], "load": raw["load"],
            "extrapolated": bool(extrapolate)}


def table(rows: list[dict]) -> str:
    lines = ["| A (px x texels) | model | in-process wall / CPU (s) | cluster | cluster start CPU (s) | "
             "transport on the cluster wall / CPU (s) | CPU overhead | shards (count, compute s) | shard CPU (s) | "
             "driver's own (s) | projected wall | max rel. diff A / Gram | load |",
             "|---|---|---:|---|---:|---:|---:|---|---|---:|---|---|---|"]
    for r in rows:
        if r["extrapolated"]:
            pj = ", ".join(f"{w} workers {t:.0f} s ({r['wall_in'] / t:.1f}x)" for w, t in r["proj"].items())
            sh = ", ".join(f"{k} {n} / {s:.0f}" for k, (n, s) in r["shards"].items())
            lines.append(f"| {r['shape']} | {r['model']} | ~{r['wall_in']:.0f} / - | simulated | - | - | - | {sh} | - | "
                         f"{r['driver']:.1f} | {pj} | - | - |")
            continue
        sh = ", ".join(f"{k} {n} / {s:.1f}" for k, (n, s) in r["shards"].items())
        pj = ", ".join(f"{w} workers {t:.1f} s ({r['wall_in'] / t:.1f}x)" for w, t in r["proj"].items())
        lines.append(f"| {r['shape']} | {r['model']} | {r['wall_in']:.1f} / {r['cpu_in']:.1f} | local:{r['workers']} | "
                     f"{r['start_cpu']:.1f} | {r['wall_d']:.1f} / {r['cpu_d']:.1f} | "
                     f"{100 * (r['cpu_d'] / r['cpu_in'] - 1):+.0f}% | {sh} | "
                     f"{', '.join(f'{k} {v:.1f}' for k, v in r['shard_cpu'].items())} | {r['driver']:.1f} | {pj} | "
                     f"{r['max_rel_A']:.1e} / {r['max_rel_gram']:.1e} | {r['load'][0]:.1f}-{r['load'][1]:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from bench.sections import invocation, write_section

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--env-height", type=int, nargs="+", default=[32])
    ap.add_argument("--project", type=int, nargs="+", default=[8])
    ap.add_argument("--extrapolate", type=int, default=None, metavar="H",
                    help="also project to env_height H from the first run's per-shard timings (columns x texels, "
                         "Gram x texels^2)")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    raws = [measure(args.workers, h) for h in args.env_height]
    rows = [summarize(r, args.project) for r in raws]
    if args.extrapolate:
        rows.append(summarize(raws[0], args.project, args.extrapolate))
    body = f"{invocation('bench.cluster_bench', argv)}\n\n{table(rows)}"
    print(body)
    if args.write:
        write_section("cluster", body, "Past one machine: the transport on a Dask cluster (issue 25)")


if __name__ == "__main__":
    main()
