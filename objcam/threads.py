"""BLAS threading: solver code runs with one BLAS thread (OpenBLAS's 2 threads made Cholesky several times and
L-BFGS-B up to 30x slower and erratic on the 2-core machines objcam targets). Large products are the exception:
a 16,384 x 1,088 float32 Gram matrix took 0.18 s on one thread and 0.11 s on two (:func:`blas_threads` around
just that product)."""

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


@contextmanager
def blas_threads(n: int | None = None):
    """Let BLAS use ``n`` threads (default: every core, :func:`cores`) inside, e.g. for one large matrix product
    in solver code that otherwise runs under :func:`single_blas_thread`."""
    with _controller().limit(limits=int(n or cores()), user_api="blas"):
        yield


def cores() -> int:
    """The CPU cores this process may run on."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def parallel_map(fn, items, workers: int | None = None) -> list:
    """``[fn(item) for item in items]`` on a pool of threads, one per core (at most one per item).

    For independent dense-linear-algebra tasks (e.g. the exact QPs of one x-step, each a Cholesky and triangular
    solves): LAPACK releases the GIL, so with one BLAS thread per task (the caller holds
    :func:`single_blas_thread`) two tasks use both cores without BLAS's own threading, which is what made
    single factorisations slower here. Exceptions propagate; the order of the results is that of ``items``."""
    items = list(items)
    n = min(len(items), int(workers or cores()))
    if n <= 1:
        return [fn(it) for it in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(fn, items))
