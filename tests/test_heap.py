"""objcam.heap: freed memory kept for reuse while a stage runs (glibc's mallopt), restored afterwards."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from objcam import heap

MB40 = 40 * 2**20  # above glibc's largest dynamic mmap threshold (32 MB)


class _MallInfo2(ctypes.Structure):
    _fields_ = [(f, ctypes.c_size_t) for f in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                                                "uordblks", "fordblks", "keepcost")]


def _info() -> _MallInfo2:
    libc = heap._libc()
    libc.mallinfo2.restype = _MallInfo2
    return libc.mallinfo2()


def _mapped_while_alive() -> tuple[int, int, int]:
    """(bytes of mmapped blocks gained while an array lives, heap bytes given back when it is freed, its size): an
    array larger than 40 MB and than all the free memory the heaps hold (earlier tests' stages leave free blocks
    there, which glibc reuses before it maps), so where it comes from depends only on the settings."""
    size = max(MB40, int(_info().fordblks) + 64 * 2**20)
    m0 = _info().hblkhd
    a = np.ones(size // 8)
    m1, arena1 = _info().hblkhd, _info().arena
    del a
    return m1 - m0, arena1 - _info().arena, size


@pytest.mark.skipif(heap._libc() is None or not hasattr(heap._libc(), "mallinfo2"),
                    reason="glibc (>= 2.33) only: elsewhere reuse_freed_memory is a no-op")
def test_large_arrays_come_from_the_heap_and_stay_there_inside_and_glibc_defaults_come_back_after():
    """Inside, a large array is served from the heap, not a fresh mapping (whose pages the kernel zeroes again on
    every first touch: the 2.1-2.6 s of system time in the demo's transport), and freeing it keeps the heap;
    outside (before, and after the block, nested or not) it is a mapping again. Broken versions: mallopt not
    called (inside mapped as outside), or not undone (after: still from the heap)."""
    mapped, _, size = _mapped_while_alive()
    assert mapped >= size
    with heap.reuse_freed_memory() as changed:
        assert changed
        with heap.reuse_freed_memory():  # nested: the outer block restores
            pass
        mapped, given_back, _ = _mapped_while_alive()
        assert mapped == 0 and given_back == 0
    mapped, _, size = _mapped_while_alive()
    assert mapped >= size
