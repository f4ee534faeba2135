"""BLAS threading: solver code runs with one BLAS thread (OpenBLAS's 2 threads made Cholesky several times and
L-BFGS-B up to 30x slower and erratic on the 2-core machines objcam targets)."""

from __future__ import annotations

from contextlib import contextmanager
from functools import lru_cache


@lru_cache(maxsize=1)
def _controller():
    # building the controller scans the loaded libraries (~5 ms): do it once, not on every solve
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextmanager
def single_blas_thread():
    with _controller().limit(limits=1, user_api="blas"):
        yield
