"""Numpy arrays handed to Dr.Jit and Embree, padded so that their vector loads stay in bounds.

Dr.Jit (1.x, LLVM backend) maps a contiguous numpy array into a Dr.Jit array without copying it, and a kernel
that reads such an array elementwise loads whole vectors (16 lanes with AVX-512) up to the last element: it
reads up to a vector's width past the end of the numpy buffer. Embree reads a mesh's last vertex (three floats)
with a 16-byte load. Past the end of a buffer that closes its memory mapping (glibc serves allocations of 128 KiB
and more by mmap; with MALLOC_TRIM_THRESHOLD_ set, as Dask's nanny sets it for its workers, that threshold never
grows, so many more arrays are mapped) the read faults: the segfaults of issue 25 (bench/results.md; a minimal
repro: tests/test_dr_memory.py). Every numpy array objcam gives Dr.Jit or Mitsuba goes through :func:`padded`:
a contiguous copy followed by :data:`PAD_BYTES` of zeros that such reads land in.
"""

from __future__ import annotations

import numpy as np

#: bytes after the last element: a 16-lane vector of 8-byte elements, twice
PAD_BYTES = 256


def padded(a, dtype=None) -> np.ndarray:
    """A contiguous copy of ``a`` (as ``dtype``), same shape, inside a buffer with PAD_BYTES to spare after it."""
    a = np.asarray(a, dtype=dtype)
    n = a.size
    buf = np.zeros(n + -(-PAD_BYTES // a.dtype.itemsize), a.dtype)
    buf[:n] = a.ravel()
    return buf[:n].reshape(a.shape)
