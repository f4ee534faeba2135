"""The TV albedo prior's contrast chosen by generalised cross-validation on the noise-weighted fit (issue 29).

A free per-pixel albedo absorbs what the envmap estimate gets wrong; a total-variation prior that merges the
support into regions (objcam.solvers.albedo_tv) gives that information back to the envmap, but how strong it may be
depends on the support: a uniform one wants every pixel merged, a print's dots must stay apart. The data decide:
each candidate contrast's albedo (TV regions, each refitted by least squares) and the envmaps solved at it are one
model with ``p = C x R`` albedo parameters (R regions of estimated pixels; the envmaps' own are the same for every
candidate); its generalised cross-validation score is

    GCV = chi2 / (n - p)^2,   chi2 = sum_{p,l,m,c} (y - rho s)^2 / sigma_pl^2,   n = the data's count,

with ``sigma_pl`` the absolute noise of target l of camera p. Merging regions lowers p; GCV falls while the fit's
chi2 rises by less than about twice its own mean per parameter dropped (``2 chi2 / (n - p)``): a uniform support
merges (each merge costs only noise), dots do not (each dot pixel folded into the background costs (contrast /
noise)^2). The noise weights matter: the joint solve's unweighted data term lets the brightest illumination own
each pixel's albedo (on issue 29's family the brightest target is 12x the dimmest: its chi2 fell to 0.03 while the
dimmest rose to 2.6), so an unweighted residual would call every merge a loss.

The candidates form a ladder (``base x factor^k`` up to ``top``), scored in order; the search stops when the score
rises (past the minimum) or the partition stops changing (no region left to merge).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Candidate:
    """One contrast's score: ``contrast``, free regions ``regions``, ``chi2`` (noise-weighted residual), ``n``
    data, ``gcv`` (chi2 / (n - C R)^2, scaled by n: about 1 / n per datum at a fit to the noise)."""

    contrast: float
    regions: int
    chi2: float
    n: int
    gcv: float
    seconds: tuple[float, float] | None = None  #: (TV step, envmaps), filled by the caller
    iterations: list[int] | None = None  #: the TV step's iterations per camera

    def record(self) -> dict:
        return {"contrast": self.contrast, "regions": self.regions, "chi2_per_datum": round(self.chi2 / self.n, 5),
                "gcv": self.gcv, "seconds": self.seconds, "tv_iterations": self.iterations}


def ladder(base: float, top: float, factor: float) -> list[float]:
    """Contrasts ``base, base x factor, ...`` while <= top (at least ``base``)."""
    if not (base > 0 and factor > 1):
        return [base]
    out = [base]
    while out[-1] * factor <= top * (1 + 1e-9):
        out.append(out[-1] * factor)
    return out


def weighted_chi2(As: list[np.ndarray], Ys: list[np.ndarray], rhos: list[np.ndarray], X: np.ndarray,
                  sigmas: list[np.ndarray]) -> tuple[float, int]:
    """(chi2, n) of the model ``y_plc = rho_pc (A'_p x_lc)``: per camera A' (M_p, N), Y (M_p, L, C), rho (M_p, C),
    sigma (L,) the absolute noise of each target; X (N, L, C). n counts every (pixel, target, channel)."""
    chi2, n = 0.0, 0
    Xf = X.reshape(X.shape[0], -1)
    for A, Y, rho, sig in zip(As, Ys, rhos, sigmas):
        if A.shape[0] == 0:
            continue
        S = (np.asarray(A) @ Xf.astype(A.dtype)).astype(np.float64).reshape(Y.shape)
        r = rho[:, None, :] * S - Y
        chi2 += float(np.einsum("mlc,mlc->l", r, r) @ (1.0 / np.square(np.asarray(sig, np.float64))))
        n += r.size
    return chi2, n


def score(contrast: float, regions: int, chi2: float, n: int, channels: int) -> Candidate:
    """The candidate's GCV (module docstring), times n so that it reads ~1 for a fit at the noise."""
    dof = n - channels * regions
    return Candidate(contrast, int(regions), chi2, n, chi2 * n / dof**2 if dof > 0 else float("inf"))

