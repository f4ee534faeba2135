"""The transport's size before it is built, and the known-albedo solve's after it: memory and time from the pixel
and texel counts, refused when the machine cannot hold it (``--set transport.env_height=256`` on a capture
without a support plane would need float64 Gram matrices of ~0.4 TB).

What is counted, per camera (``channels`` 1 for a grey albedo, else 3; N the texels A keeps):

* A as float32: pixels x N x channels x 4 bytes;
* the Gram matrices A_c^T A_c as float64 (channels x N^2 x 8), stored beside A and read by the solve;
* the solve's working copies, ``SOLVE_COPIES`` x N^2 x 8 bytes per channel (an upper bound: the merged basis
  has fewer unknowns than A has texels, ~0.6 N^2 at 128 x 256): the Gram matrix less the unusable pixels' rows
  while it is merged, the merged Gram matrix (objcam.solvers.basis.merge_gram, shared by the edge prior's
  luminance and chroma solves, which run side by side), its outlier downdates (objcam.solvers.plan.known), and
  the verdict's float32 factor. Above objcam.solvers.nnls.PCG_MIN_UNKNOWNS the solves form no regularised Gram
  matrix of their own (objcam.solvers.products.GramPlusSparse); below it the Cholesky paths' copies are small.
  gram.npy itself is memory-mapped (its pages are the file's, counted once in the Gram term).

N: with a support plane A keeps the texels above its horizon and the row below it (the sky a pixel near the
plane's edge sees past it): ``(H/2 + 1) x 2H`` (measured: 1,088 at 32 x 64, 4,224 at 64 x 128 on the demo); without
one every texel. Time: the columns of A, the Gram product, and per target the edge solve (~N^2 on
its PCG path) and its verdict's factorisation (N^3), each from a rate measured on this project's 2-core machine
(constants below). :func:`plan` sums a build's cameras; the transport stage and ``transport.env_height=auto``
(objcam.transport.resolution.affordable) plan with the same estimates.
"""

from __future__ import annotations

import os

from objcam.errors import StageError

# Seconds per (pixel, texel) pair of A, measured on the core bench (2 cores: auto 10.5 s for 16,384 x 1,088 pairs,
# supersample 2: 30.2 s for 16,384 x 4,224), and Gram flops per second (numpy BLAS on the same machine).
SECONDS_PER_PAIR = 6e-7
GRAM_FLOPS = 2e10
MEMORY_SHARE = 0.8  # of the machine's physical memory one build may plan to use
# The known-albedo edge solve's working set per channel, in N^2 float64 copies (module docstring). Checked against
# the solve stage's peak at 128 x 256 (demo capture, direct A, one outlier downdate; bench/results.md, issue 26
# session 24): 6.8 GiB RSS with A and the Gram file's pages, against 9.2 GiB estimated (it was 5 copies, 13.4 GiB,
# while every solve formed its own Q: peak 9.3 GiB).
SOLVE_COPIES = 3
# The default edge solve's CPU seconds per target per texel^2 (the PCG free-block path of objcam.solvers.nnls,
# session 18; solve.json's solve_cpu_seconds): 140 s at 16,640 texels (128 x 256, the forest synth capture, 12,744
# unknowns after merging, quiet machine, 2026-12-04), 7.5-11.0 s at 4,224 (64 x 128, forest and courtyard
# captures, load 4-10), 0.4-0.9 s at 1,088 (32 x 64, the resolution bench's four HDRIs; the Cholesky path below
# 1,024 unknowns). Between each pair the time grows as ~N^1.95, not the Cholesky path's N^3 (3.3e-10 N^3 planned
# 1,520 s at 128 x 256): 5.1e-7 N^2 gives 140 / 9.1 / 0.60 s.
SOLVE_SECONDS_PER_TEXEL2 = 5.1e-7
# The verdict's texel uncertainty (objcam.solvers.plan.verdict): one float32 Cholesky of the N x N Q (N^3 / 3
# flops, ~80 GFlop/s on one core) and the inverse of the block the texels' lower bounds leave undecided: measured
# 21-35 s on one core at 16,640 texels (bench/results.md, issue 26, session 19), planned at its full N^3 / 3 x 2.
VERDICT_SECONDS_PER_TEXEL3 = 8.5e-12


def machine_memory() -> int:
    """Physical memory in bytes (0 when unknown)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 0


def kept_texels(env_height: int, support_plane: bool) -> int:
    """Texels A will keep (an upper bound): above a support plane's horizon plus the row below it, else all."""
    h, w = int(env_height), 2 * int(env_height)
    return min(h, h // 2 + 1) * w if support_plane else h * w


def estimate(pixels: int, texels: int, channels: int = 3, targets: int = 1) -> dict:
    """Peak bytes and seconds of one camera's A, Gram matrices and known-albedo solves of its ``targets`` (module
    docstring). Returns {"bytes", "seconds", "pixels", "texels", "channels", "targets", "parts": {name: bytes or
    seconds}}."""
    a_bytes = 4 * pixels * texels * channels
    gram_bytes = 8 * channels * texels * texels
    solve_bytes = SOLVE_COPIES * gram_bytes
    a_s = SECONDS_PER_PAIR * pixels * texels
    gram_s = pixels * texels * texels * channels / GRAM_FLOPS
    n = float(texels)
    # per target, three colour columns with any channel count; the targets are solved one after another
    solve_s = targets * (SOLVE_SECONDS_PER_TEXEL2 * n**2 + VERDICT_SECONDS_PER_TEXEL3 * n**3)
    return {"bytes": a_bytes + gram_bytes + solve_bytes, "seconds": a_s + gram_s + solve_s, "pixels": pixels,
            "texels": texels, "channels": channels, "targets": targets,
            "parts": {"a_bytes": a_bytes, "gram_bytes": gram_bytes, "solve_bytes": solve_bytes,
                      "a_seconds": a_s, "gram_seconds": gram_s, "solve_seconds": solve_s}}


def plan(ests: list[dict]) -> dict:
    """A build's plan from its cameras' estimates: {"bytes": the largest peak (cameras are built one after
    another), "seconds": the summed time}."""
    return {"bytes": max(e["bytes"] for e in ests), "seconds": sum(e["seconds"] for e in ests)}


def check(est: dict, toml, memory: int | None = None) -> None:
    """Refuse a build past ``MEMORY_SHARE`` of the machine's memory, naming the numbers and what to change."""
    memory = machine_memory() if memory is None else memory
    if memory and est["bytes"] > MEMORY_SHARE * memory:
        raise StageError(f"the transport and its solve would need about {est['bytes'] / 2**30:,.1f} GiB of memory "
                         f"({est['pixels']:,} pixels x {est['texels']:,} texels; about {est['seconds'] / 3600:,.1f} h)"
                         f" and this machine has {memory / 2**30:,.1f} GiB", toml,
                         "lower transport.env_height (or transport.supersample, transport.max_pixels)")
