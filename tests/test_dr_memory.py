"""objcam.dr_memory: Dr.Jit reads numpy arrays it was handed past their end (a minimal repro of issue 25's
segfaults, in a subprocess), and the padded copies objcam hands it instead keep those reads in bounds."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np

from objcam.dr_memory import PAD_BYTES, padded

# an array placed so that its last byte is the last one before a PROT_NONE page: a read past its end faults
SCRIPT = textwrap.dedent("""
    import ctypes, mmap, sys
    import numpy as np
    import drjit as dr, mitsuba as mi
    from objcam.dr_memory import PAD_BYTES
    mi.set_variant("llvm_ad_rgb")
    libc = ctypes.CDLL(None)
    pad = PAD_BYTES // 4 if sys.argv[1] == "padded" else 0
    for n in (3, 17, 1000, 4099):
        total = 4 * (n + pad)
        pages = -(-total // mmap.PAGESIZE) + 1
        buf = mmap.mmap(-1, pages * mmap.PAGESIZE)
        at = ctypes.addressof(ctypes.c_char.from_buffer(buf))
        assert libc.mprotect(ctypes.c_void_p(at + (pages - 1) * mmap.PAGESIZE), mmap.PAGESIZE, 0) == 0
        a = np.frombuffer(buf, np.float32, n + pad, (pages - 1) * mmap.PAGESIZE - total)[:n]
        a[:] = np.arange(n)
        x = mi.Float(a)  # mapped, not copied
        y = x * 2.0 + 1.0
        dr.eval(y)
        assert np.array_equal(np.asarray(y), 2.0 * np.arange(n) + 1.0)
    print("in bounds")
""")


def _run(mode: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, timeout=300)


def test_padded_copies_keep_drjit_kernels_in_bounds():
    a = np.arange(12, dtype=np.float64).reshape(4, 3)[:, 1]  # strided view
    p = padded(a, np.float32)
    assert p.dtype == np.float32 and p.flags.c_contiguous and np.array_equal(p, a)
    assert p.base.nbytes - p.nbytes >= PAD_BYTES and not np.shares_memory(p, a)
    assert padded(np.ones((2, 5), np.uint32)).shape == (2, 5)
    ok = _run("padded")
    assert ok.returncode == 0 and "in bounds" in ok.stdout, ok.stderr[-2000:]
    # the test of the test: the same arrays without the padding fault (Dr.Jit 1.x's elementwise kernels load
    # whole vectors up to the last element); should a Dr.Jit release stop doing so, this fails and says so
    bad = _run("unpadded")
    assert bad.returncode < 0, ("Dr.Jit no longer reads past a mapped numpy array's end: objcam.dr_memory's "
                                "padding may be unnecessary", bad.returncode, bad.stderr[-500:])
