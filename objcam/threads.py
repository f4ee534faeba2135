"""BLAS threading: solver code runs with one BLAS thread (OpenBLAS's 2 threads made Cholesky several times and
L-BFGS-B up to 30x slower and erratic on the 2-core machines objcam targets)."""

from __future__ import annotations

from contextlib import contextmanager


@contextmanager
def single_blas_thread():
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield
