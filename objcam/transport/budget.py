"""The transport's size before it is built: memory and time from the pixel and texel counts, refused when the
machine cannot hold it (``--set transport.env_height=256`` would need a float64 Gram matrix of ~0.4 TB)."""

from __future__ import annotations

import os

from objcam.errors import StageError

# Seconds per (pixel, texel) pair of A, measured on the core bench (2 cores: auto 10.5 s for 16,384 x 1,088 pairs,
# supersample 2: 30.2 s for 16,384 x 4,224), and Gram flops per second (numpy BLAS on the same machine).
SECONDS_PER_PAIR = 6e-7
GRAM_FLOPS = 2e10
MEMORY_SHARE = 0.8  # of the machine's physical memory one build may plan to use


def machine_memory() -> int:
    """Physical memory in bytes (0 when unknown)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 0


def estimate(pixels: int, texels: int, channels: int = 3) -> dict:
    """Peak bytes (A as float32, the Gram matrix and the solve's factor as float64) and seconds of one camera."""
    a_bytes = 4 * pixels * texels * channels
    gram_bytes = 8 * channels * texels * texels
    seconds = SECONDS_PER_PAIR * pixels * texels + pixels * texels * texels * channels / GRAM_FLOPS
    return {"bytes": a_bytes + 2 * gram_bytes, "seconds": seconds, "pixels": pixels, "texels": texels}


def check(est: dict, toml, memory: int | None = None) -> None:
    """Refuse a build past ``MEMORY_SHARE`` of the machine's memory, naming the numbers and what to change."""
    memory = machine_memory() if memory is None else memory
    if memory and est["bytes"] > MEMORY_SHARE * memory:
        raise StageError(f"the transport would need about {est['bytes'] / 2**30:,.1f} GiB of memory "
                         f"({est['pixels']:,} pixels x {est['texels']:,} texels; about {est['seconds'] / 3600:,.1f} h) "
                         f"and this machine has {memory / 2**30:,.1f} GiB", toml,
                         "lower transport.env_height (or transport.supersample, transport.max_pixels)")
