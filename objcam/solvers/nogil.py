"""LAPACK's Cholesky and triangular solves, and BLAS's symmetric matrix-vector product, without holding Python's GIL.

scipy's LAPACK wrappers (``scipy.linalg.lapack``, ``cho_factor``, ``solve_triangular``) hold the GIL while LAPACK
runs, so the luminance and chroma edge solves on their two threads (objcam.threads.parallel_map) took turns at
every factorisation of the 32 x 64 solve: two threads doing 30 Cholesky factorisations of an 800 x 800 matrix
each took as long as one thread doing 60 (0.49 against 0.52 s), where a numpy product, which releases it, took
0.17 against 0.30 s (bench/results.md, issue 26 session 20). These call the same routines of the same library
(scipy's ``cython_lapack`` function pointers) through ctypes, which releases the GIL during a foreign call:
the same numbers, bitwise, as the scipy wrappers for the same arguments.

The conventions follow the f2py wrappers: an argument that is not Fortran-ordered float64 is copied to one
(so the matrix LAPACK sees is the logical matrix given), and the factor is upper (``A = U^T U``).
"""

from __future__ import annotations

import ctypes

import numpy as np

_c_int_p = ctypes.POINTER(ctypes.c_int)
_fns: dict[str, object] = {}


def _fn(name: str, nargs: int, blas: bool = False):
    """The ctypes function for cython_lapack's (or, with ``blas``, cython_blas's) ``name`` (every argument a
    pointer; returns void)."""
    f = _fns.get(name)
    if f is None:
        from scipy.linalg import cython_blas, cython_lapack

        cap = (cython_blas if blas else cython_lapack).__pyx_capi__[name]
        api = ctypes.pythonapi
        api.PyCapsule_GetName.restype = ctypes.c_char_p
        api.PyCapsule_GetName.argtypes = [ctypes.py_object]
        api.PyCapsule_GetPointer.restype = ctypes.c_void_p
        api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        ptr = api.PyCapsule_GetPointer(cap, api.PyCapsule_GetName(cap))
        # CFUNCTYPE (not PYFUNCTYPE): ctypes releases the GIL for the call
        f = _fns[name] = ctypes.CFUNCTYPE(None, *([ctypes.c_void_p] * nargs))(ptr)
    return f


def _call(name: str, *args) -> int:
    """cython_lapack's ``name`` on ``args`` (a char for a str, an int for an int, a double for a float, a pointer
    for a float64 array's data); returns the trailing info argument (an int output, passed last). The scalars
    are held here for the call's duration."""
    held = []
    for a in args:
        if isinstance(a, np.ndarray):
            held.append(ctypes.c_void_p(a.ctypes.data))
        elif isinstance(a, str):
            held.append(ctypes.c_char(a.encode()))
        elif isinstance(a, float):
            held.append(ctypes.c_double(a))
        else:
            held.append(ctypes.c_int(int(a)))
    info = ctypes.c_int(0)
    ptrs = [ctypes.byref(h) if not isinstance(h, ctypes.c_void_p) else h for h in held]
    _fn(name, len(args) + 1)(*ptrs, ctypes.byref(info))
    return int(info.value)


def _fortran(a: np.ndarray, overwrite: bool) -> np.ndarray:
    """a as a Fortran-ordered float64 array: a itself when ``overwrite`` and it already is one, else a copy."""
    if overwrite and a.dtype == np.float64 and a.flags.f_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64, order="F", copy=True)


def _2d(b: np.ndarray) -> tuple[np.ndarray, bool]:
    b = np.asarray(b)
    return (b[:, None], True) if b.ndim == 1 else (b, False)


def _laset_args(sub: np.ndarray, m: int, lda: int) -> list:
    """dlaset's arguments setting the lower triangle and diagonal of the m x m block at ``sub`` (leading
    dimension lda) to 0."""
    # (a byref holds its object: the scalars live as long as the returned list)
    return [ctypes.byref(ctypes.c_char(b"L")), ctypes.byref(ctypes.c_int(m)), ctypes.byref(ctypes.c_int(m)),
            ctypes.byref(ctypes.c_double(0.0)), ctypes.byref(ctypes.c_double(0.0)), ctypes.c_void_p(sub.ctypes.data),
            ctypes.byref(ctypes.c_int(lda))]


def potrf(a: np.ndarray, overwrite: bool = False, clean: bool = True) -> tuple[np.ndarray, int]:
    """(U, info): the upper Cholesky factor of the symmetric a (n, n) (its upper triangle read), Fortran-ordered;
    as ``scipy.linalg.lapack.dpotrf(a, lower=0, clean=clean, overwrite_a=overwrite)``. info > 0: not positive
    definite (U is then not a factor). ``clean``: the strict lower triangle zeroed."""
    c = _fortran(a, overwrite)
    n = c.shape[0]
    info = _call("dpotrf", "U", n, c, max(1, n))
    if clean and n > 1:
        # the strict lower triangle zeroed by LAPACK's dlaset on c[1:, :n-1] (its lower triangle and diagonal):
        # a numpy mask over the N^2 entries cost a third of the factorisation at N = 800
        _fn("dlaset", 7)(*_laset_args(c[1:, :], n - 1, n))
    return c, info


def potrs(c: np.ndarray, b: np.ndarray, overwrite_b: bool = False) -> tuple[np.ndarray, int]:
    """(x, info): A^-1 b from A's upper Cholesky factor c (n, n) (:func:`potrf`); b (n,) or (n, m); as
    ``scipy.linalg.lapack.dpotrs(c, b, lower=0)``."""
    c = c if c.flags.f_contiguous and c.dtype == np.float64 else np.asfortranarray(c, dtype=np.float64)
    b2, vec = _2d(b)
    x = _fortran(b2, overwrite_b)
    n, m = x.shape
    info = _call("dpotrs", "U", n, m, c, max(1, c.shape[0]), x, max(1, n))
    return (x[:, 0] if vec else x), info


def trtrs(a: np.ndarray, b: np.ndarray, trans: bool = False, lower: bool = False,
          overwrite_b: bool = False) -> np.ndarray:
    """``op(a)^-1 b`` for the triangular a (n, n) (upper unless ``lower``; op: transpose when ``trans``), b (n,)
    or (n, m); as ``scipy.linalg.solve_triangular(a, b, trans=trans, lower=lower)`` (a C-ordered a is solved
    as its transpose with the other triangle, as scipy does). Raises LinAlgError for a zero diagonal."""
    if not a.flags.f_contiguous:
        a, trans, lower = a.T, not trans, not lower
        if not a.flags.f_contiguous or a.dtype != np.float64:
            a = np.asfortranarray(a, dtype=np.float64)
    elif a.dtype != np.float64:
        a = np.asfortranarray(a, dtype=np.float64)
    b2, vec = _2d(b)
    x = _fortran(b2, overwrite_b)
    n, m = x.shape
    info = _call("dtrtrs", "L" if lower else "U", "T" if trans else "N", "N", n, m, a, max(1, a.shape[0]), x,
                 max(1, n))
    if info > 0:
        raise np.linalg.LinAlgError(f"singular matrix: resolution failed at diagonal {info - 1}")
    return x[:, 0] if vec else x


def cho_factor(a: np.ndarray) -> np.ndarray:
    """The upper Cholesky factor of a (its strict lower triangle not zeroed), for :func:`cho_solve`; as
    ``scipy.linalg.cho_factor(a)[0]``. Raises LinAlgError when a is not positive definite."""
    c, info = potrf(a, clean=False)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor of the array is not positive definite")
    return c


def cho_solve(c: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A^-1 b from :func:`cho_factor`'s c; as ``scipy.linalg.cho_solve((c, False), b)``."""
    x, info = potrs(c, b)
    if info != 0:
        raise ValueError(f"illegal value in {-info}th argument of internal potrs")
    return x


def symv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``a v`` (n, m), Fortran-ordered, for a symmetric float64 a (n, n), C- or Fortran-contiguous, and v (n,) or
    (n, m): BLAS dsymv once per column, which reads one triangle of a (half the memory of a general product).
    For the few columns of an iterative solver's product it is 2-3x faster than a matrix product, whose packing
    of a is paid per call (3,136 x 3,136, 3 columns, one core: 4.4 against 8-10 ms), and the GIL is released,
    so the luminance and chroma solves' products overlap. Only the stored triangle is read: a must be symmetric."""
    n = a.shape[0]
    if a.ndim != 2 or a.shape != (n, n) or a.dtype != np.float64:
        raise ValueError(f"symv: a must be a square float64 matrix, got {a.shape} {a.dtype}")
    if not (a.flags.c_contiguous or a.flags.f_contiguous):
        a = np.ascontiguousarray(a)
    v2, vec = _2d(v)
    if v2.shape[0] != n:
        raise ValueError(f"symv: a is {a.shape}, v has {v2.shape[0]} rows")
    # contiguous float64 columns: dsymv with a strided x (incx > 1) ran ~4x slower
    v2 = np.asfortranarray(v2, dtype=np.float64)
    m = v2.shape[1]
    y = np.zeros((n, m), order="F")
    if n == 0 or m == 0:
        return y[:, 0] if vec else y
    f = _fn("dsymv", 10, blas=True)
    held = [ctypes.c_char(b"L"), ctypes.c_int(n), ctypes.c_double(1.0), ctypes.c_int(n), ctypes.c_int(1),
            ctypes.c_double(0.0), ctypes.c_int(1)]
    uplo, nn, alpha, lda, incx, beta, incy = (ctypes.byref(h) for h in held)
    for j in range(m):
        f(uplo, nn, alpha, ctypes.c_void_p(a.ctypes.data), lda, ctypes.c_void_p(v2.ctypes.data + j * v2.strides[1]),
          incx, beta, ctypes.c_void_p(y.ctypes.data + j * y.strides[1]), incy)
    return y[:, 0] if vec else y
