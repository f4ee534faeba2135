"""The GPU half of the variant bench (issue 25), for a lent GPU machine that has no libLLVM and no registry.

    python -m bench.variant_device CAPTURE OUT [--builds cuda:0:direct:32,...]

Builds the transport stage of CAPTURE (a capture whose ``scene`` stage is already in ``CAPTURE/objcam/scene``:
bench.cluster_bench's ``_capture()``, make demo's) once per build spec ``VARIANT:SEED:MODEL:ENV_HEIGHT``, each in its
own process (Mitsuba's variant is process-wide), and writes ``OUT/timings.json`` (wall and CPU seconds per build,
the variant the stage reports, the GPU's name) and, for the specs named by ``--keep``, ``OUT/NAME.npz`` holding the
build's A on every ``COLUMN_STRIDE``-th texel by texel index (chosen without looking at A) with its texel and pixel
indices, so that ``python -m bench.variant_bench --cuda-from OUT`` compares it here against llvm builds of the same
capture (the whole A of the interreflection model is ~40 MB compressed, past what such a machine returns). The first build of a variant compiles
Dr.Jit's kernels (cached on disk afterwards): run a spec twice to see the warm time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

COLUMN_STRIDE = 8  # every 8th texel index: ~1/8 of A's columns, spread over the whole envmap

_BUILD = """
import json, sys, time
from pathlib import Path
from objcam.pipeline.stage import StageInputs
from objcam.stages import transport as stage
cap, out, variant, seed, model, h = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4]), sys.argv[5], int(sys.argv[6])
out.mkdir(parents=True)
t0, c0 = time.perf_counter(), time.process_time()
m = stage.run(StageInputs(capture=cap, upstream={"scene": cap / "objcam" / "scene"}, out=out, quiet=True),
              stage.Params(variant=variant, seed=seed, model=model, env_height=h)).metrics
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0, "variant": m["variant"],
                  "model": m.get("model"), "texels": m.get("texels"), "pixels": m.get("pixels")}))
"""


def build(cap: Path, out: Path, spec: str, timeout: float) -> dict:
    """One transport build in a fresh process; returns its timings (or the error's last line)."""
    variant, seed, model, height = spec.split(":")
    t0 = time.perf_counter()
    try:
        r = subprocess.run([sys.executable, "-c", _BUILD, str(cap), str(out), variant, seed, model, height],
                           capture_output=True, text=True, timeout=timeout, env={**os.environ, "OBJCAM_QUIET": "1"})
    except subprocess.TimeoutExpired:
        return {"spec": spec, "error": f"timed out after {timeout:.0f} s"}
    if r.returncode != 0:
        tail = (r.stderr.strip() or str(r.returncode)).splitlines()[-3:]
        return {"spec": spec, "error": " | ".join(tail), "process_wall": time.perf_counter() - t0}
    return {"spec": spec, "process_wall": time.perf_counter() - t0} | json.loads(r.stdout.strip().splitlines()[-1])


def column_subset(group: Path, stride: int = COLUMN_STRIDE) -> dict[str, np.ndarray]:
    """A (channels x pixels x kept texels, float32) on the texels whose index is a multiple of ``stride`` (1: all),
    with ``texel_index`` (those texels) and ``pixel_index`` (all of A's pixels)."""
    from objcam.transport.storage import load_group

    t = load_group(group)
    sel = np.flatnonzero(t.texel_index % stride == 0)
    return {"A": np.ascontiguousarray(t.A[:, :, sel]), "texel_index": t.texel_index[sel], "pixel_index": t.pixel_index}


def gpu_name() -> str:
    try:
        return subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                              capture_output=True, text=True, timeout=30).stdout.strip()
    except Exception as e:  # no nvidia-smi: say so rather than fail the bench
        return f"unknown ({e})"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--builds", default="cuda:0:direct:32,cuda:0:direct:32,cuda:1:direct:32,cuda:0:auto:32,"
                                        "cuda:0:direct:64,cuda:0:direct:128,llvm:0:direct:32")
    ap.add_argument("--keep", default="cuda:0:direct:32,cuda:0:auto:32", help="specs whose cam0 group is returned")
    ap.add_argument("--timeout", type=float, default=240.0, help="seconds per build")
    ap.add_argument("--work", type=Path, default=Path("/tmp/variant_device"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    keep = set(args.keep.split(",")) if args.keep else set()
    rows, kept = [], set()
    for i, spec in enumerate(args.builds.split(",")):
        out = args.work / f"{i}_{spec.replace(':', '_')}"
        row = build(args.capture, out, spec, args.timeout)
        rows.append(row)
        print(json.dumps(row), flush=True)
        if spec in keep and spec not in kept and "error" not in row:
            np.savez(args.out / f"{spec.replace(':', '_')}.npz", **column_subset(out / "cam0"))
            kept.add(spec)
        (args.out / "timings.json").write_text(json.dumps({"gpu": gpu_name(), "builds": rows}, indent=1))


if __name__ == "__main__":
    main()
