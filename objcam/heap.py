"""Freed memory kept for reuse while a stage runs (glibc's malloc; a no-op elsewhere).

glibc serves every allocation of 128 KiB or more (a threshold it raises, up to 32 MiB, as large blocks are freed)
by a fresh memory mapping, and returns it to the kernel when the block is freed. A stage that builds A makes and
drops thousands of such arrays (an (M, B) classification mask, a (C, M, B) block of columns, a float64 row block
of the Gram matrix), so each of them costs page faults: the kernel zeroes every page again on first touch. On the
demo's transport that was 2.1-2.6 s of system time in an 11 s stage (bench/results.md, issue 25, session 35).

:func:`reuse_freed_memory` turns the mappings off (``M_MMAP_MAX`` = 0: large blocks come from the heap) and
keeps freed memory in the heap (``M_TRIM_THRESHOLD`` very large) while it is held, then restores glibc's defaults
(or the ``MALLOC_TRIM_THRESHOLD_`` the environment set, as Dask's nanny does) and hands the free heap back to the
kernel (``malloc_trim``). The peak memory is the same: a block is reused, not duplicated. It also keeps the
over-reads objcam.dr_memory guards against inside the heap.
"""

from __future__ import annotations

import ctypes
import os
import threading
from contextlib import contextmanager
from functools import lru_cache

# mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
#: glibc's defaults, restored on exit
_DEFAULT_MMAP_MAX = 65536
_DEFAULT_TRIM_THRESHOLD = 128 * 1024
#: keep this much freed memory in the heap (the largest value mallopt takes, an int)
_KEEP = 2**31 - 1

_lock = threading.Lock()
_depth = 0


@lru_cache(maxsize=1)
def _libc():
    """glibc's mallopt / malloc_trim, or None (another C library, or not Linux)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        libc.malloc_trim.argtypes, libc.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
        return libc
    except (OSError, AttributeError):
        return None


def _trim_default() -> int:
    try:
        return int(os.environ.get("MALLOC_TRIM_THRESHOLD_", _DEFAULT_TRIM_THRESHOLD))
    except ValueError:
        return _DEFAULT_TRIM_THRESHOLD


@contextmanager
def reuse_freed_memory():
    """Large arrays from the heap, and freed memory kept for the next one, inside; nests (the outermost restores).
    Returns whether glibc's settings were changed."""
    global _depth
    libc = _libc()
    with _lock:
        outer = _depth == 0
        _depth += 1
        if outer and libc is not None:
            libc.mallopt(_M_MMAP_MAX, 0)
            libc.mallopt(_M_TRIM_THRESHOLD, _KEEP)
    try:
        yield libc is not None
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and libc is not None:
                libc.mallopt(_M_MMAP_MAX, _DEFAULT_MMAP_MAX)
                libc.mallopt(_M_TRIM_THRESHOLD, _trim_default())
                libc.malloc_trim(0)
