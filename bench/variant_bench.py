"""A from Mitsuba's cuda_ad_rgb against llvm_ad_rgb on the demo capture (issue 25), within the Monte Carlo
tolerance: the two variants' A differ by their floating-point paths only (same seeds, same rays), so their
difference must stay within the difference between two llvm builds of different seeds, which is the Monte Carlo
noise itself.

    python -m bench.variant_bench [--model direct] [--write]      # needs a CUDA device (transport.variant=cuda)
    python -m bench.variant_bench --cuda-from DIR [--write]       # DIR: bench.variant_device's output from a GPU

The second form is for a GPU machine lent without this project's set-up: bench.variant_device builds there and
returns A on every 8th texel (by index) of each kept build with its timings; the llvm builds run here, and the
comparison is on those columns.

Each build runs in its own process (Mitsuba's variant is process-wide). Reports per build the wall and CPU
seconds, and the relative Frobenius and largest column differences of cuda against llvm (seed 0) and of llvm
seed 1 against llvm seed 0. With ``--write`` the table goes to bench/results.md's ``variant`` block.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

OUT = Path("bench/out/variant")


def _build(cap: Path, name: str, variant: str, seed: int, model: str) -> dict:
    """The transport of ``cap`` at 32 x 64 in its own process into OUT/name (bench.variant_device.build); its
    timings with ``out``, or SystemExit naming the build and its error."""
    import shutil

    from bench.variant_device import build

    out = OUT / name
    shutil.rmtree(out, ignore_errors=True)
    row = build(cap, out, f"{variant}:{seed}:{model}:32", timeout=3600.0)
    if "error" in row:
        raise SystemExit(f"{name}: {row['error']}")
    return row | {"out": out}


def _diff(a: Path, b: Path) -> tuple[float, float]:
    """(relative Frobenius difference, largest relative column difference) of A in b against A in a, on the
    pixels and texels both kept (seeds move edge pixels)."""
    from bench.variant_device import column_subset

    return _diff_columns(column_subset(a / "cam0", stride=1), column_subset(b / "cam0", stride=1))


def _diff_columns(a: dict, b: dict) -> tuple[float, float]:
    """(relative Frobenius difference, largest relative column difference) of b's A against a's, two
    bench.variant_device column subsets, on the pixels and texels both kept."""
    _, ia, ib = np.intersect1d(a["texel_index"], b["texel_index"], return_indices=True)
    _, pa, pb = np.intersect1d(a["pixel_index"], b["pixel_index"], return_indices=True)
    A = a["A"][:, pa][:, :, ia].astype(np.float64)
    B = b["A"][:, pb][:, :, ib].astype(np.float64)
    col = np.sqrt(((A - B) ** 2).sum(axis=(0, 1))) / np.maximum(np.sqrt((A ** 2).sum(axis=(0, 1))), 1e-30)
    return float(np.linalg.norm(A - B) / np.linalg.norm(A)), float(col.max())


def _from_device(cap: Path, folder: Path, argv) -> str:
    """The variant block from a GPU machine's bench.variant_device output in ``folder`` and llvm builds here."""
    from bench.sections import invocation
    from bench.variant_device import column_subset

    info = json.loads((folder / "timings.json").read_text())
    rows = ["| model | llvm seed 1 vs seed 0 (the Monte Carlo tolerance) | cuda seed 0 vs llvm seed 0 | within |",
            "|---|---|---|---|"]
    here = []
    for model in ("direct", "auto"):
        npz = folder / f"cuda_0_{model}_32.npz"
        if not npz.is_file():
            continue
        subsets = []
        for seed in (0, 1):
            row = _build(cap, f"llvm{seed}_{model}", "llvm", seed, model)
            here.append(row)
            subsets.append(column_subset(row["out"] / "cam0"))
        with np.load(npz) as z:
            cuda = {k: z[k] for k in z.files}
        mc, gpu = _diff_columns(subsets[0], subsets[1]), _diff_columns(subsets[0], cuda)
        ok = "yes" if gpu[0] <= mc[0] and gpu[1] <= mc[1] else "**no**"
        rows.append(f"| {model} | {mc[0]:.2e} / {mc[1]:.2e} | {gpu[0]:.2e} / {gpu[1]:.2e} | {ok} |")
    times = ["| build (variant:seed:model:env_height) | machine | wall (s) | CPU (s, all threads) |",
             "|---|---|---:|---:|"]
    seen = set()
    for r in info["builds"]:
        kind = tuple(r["spec"].split(":")[i] for i in (0, 2))  # variant and model: what a kernel is compiled for
        cold = " (first: compiles kernels)" if kind not in seen else ""
        seen.add(kind)
        if "error" in r:
            times.append(f"| {r['spec']} | GPU machine | failed: {r['error']} | |")
        else:
            times.append(f"| {r['spec']}{cold} | GPU machine | {r['wall']:.1f} | {r['cpu']:.1f} |")
    for r in here:
        times.append(f"| {r['spec']} | this machine (2 cores) | {r['wall']:.1f} | {r['cpu']:.1f} |")
    return (f"{invocation('bench.variant_bench', argv)}: builds on a lent GPU machine ({info['gpu']}, 16 CPU cores) "
            f"by `python -m bench.variant_device`, compared here on every 8th texel's column (by index, "
            f"{len(cuda['texel_index'])} columns) of the demo capture's A at 32 x 64\n\n" + "\n".join(rows)
            + "\n\n" + "\n".join(times))


def main(argv: list[str] | None = None) -> None:
    from bench.cluster_bench import _capture
    from bench.sections import invocation, write_section

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="direct", choices=["direct", "auto"])
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--cuda-from", type=Path, help="a GPU machine's `python -m bench.variant_device` output folder")
    args = ap.parse_args(argv)
    cap = _capture()
    if args.cuda_from is not None:
        body = _from_device(cap, args.cuda_from, argv)
        print(body)
        if args.write:
            write_section("variant", body, "GPU: cuda_ad_rgb against llvm_ad_rgb (issue 25)")
        return
    ref = _build(cap, "llvm0", "llvm", 0, args.model)
    other = _build(cap, "llvm1", "llvm", 1, args.model)
    cuda = _build(cap, "cuda0", "cuda", 0, args.model)
    mc, gpu = _diff(ref["out"], other["out"]), _diff(ref["out"], cuda["out"])
    rows = ["| build | wall (s) | CPU (s) | rel. difference from llvm seed 0 (all / worst column) |",
            "|---|---:|---:|---|",
            f"| llvm, seed 0 | {ref['wall']:.1f} | {ref['cpu']:.1f} | - |",
            f"| llvm, seed 1 (the Monte Carlo tolerance) | {other['wall']:.1f} | {other['cpu']:.1f} | "
            f"{mc[0]:.2e} / {mc[1]:.2e} |",
            f"| cuda, seed 0 | {cuda['wall']:.1f} | {cuda['cpu']:.1f} | {gpu[0]:.2e} / {gpu[1]:.2e} |"]
    verdict = "within" if gpu[0] <= mc[0] and gpu[1] <= mc[1] else "**outside**"
    body = (f"{invocation('bench.variant_bench', argv)}, model {args.model}\n\n" + "\n".join(rows)
            + f"\n\ncuda against llvm is {verdict} the Monte Carlo tolerance.")
    print(body)
    if args.write:
        write_section("variant", body, "GPU: cuda_ad_rgb against llvm_ad_rgb (issue 25)")


if __name__ == "__main__":
    main()
