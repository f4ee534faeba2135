"""One-dimensional minimisation shared by the solvers."""

from __future__ import annotations

from typing import Callable

import numpy as np

_INV_PHI = 0.5 * (np.sqrt(5.0) - 1.0)


def golden_section(f: Callable[[float], float], a: float, b: float, tol: float,
                   max_iter: int = 10_000) -> tuple[float, float]:
    """Golden-section search for a minimum of a unimodal ``f`` on [a, b]: shrink the bracket until it is at most
    ``tol`` wide (or ``max_iter`` steps), then return (t, f(t)) for the better of its two interior points."""
    x1, x2 = b - _INV_PHI * (b - a), a + _INV_PHI * (b - a)
    f1, f2 = f(x1), f(x2)
    for _ in range(max_iter):
        if b - a <= tol:
            break
        if f1 < f2:
            b, x2, f2 = x2, x1, f1
            x1 = b - _INV_PHI * (b - a)
            f1 = f(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + _INV_PHI * (b - a)
            f2 = f(x2)
    return (x1, f1) if f1 <= f2 else (x2, f2)
