"""Chrome-ball optics: the sphere's silhouette cone, the mirror reflection point for a direction (perspective,
exact), and the ball's reflectance (calibration factor with an optional Fresnel angular shape).

Geometry (world metres): ball centre ``C``, radius ``R``, camera centre ``O``. A distant-environment direction
``d`` (unit) is seen in the ball at the surface point ``P = C + R n`` whose normal bisects ``d`` and the unit vector
``v`` from ``P`` towards ``O``: ``n = normalise(d + v)``. Since ``v`` depends on ``P`` this is a 1D problem in the
plane of ``O - C`` and ``d`` (Alhazen's), solved by Newton's method from the orthographic guess (see
:func:`reflection_points`). The incidence angle ``i`` (between ``n`` and ``v``) satisfies ``angle(d, v) = 2 i``; ``i -> 90 deg`` is the
silhouette, where the ball shows the directions right behind itself (the blind spot).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FRESNEL_MODELS = ("none", "schlick", "conductor")

# Mitsuba 3's RGB values of its "Cr" conductor (eta, k per R, G, B): normal-incidence reflectance ~ (0.69, 0.65, 0.69).
CHROME_ETA = (4.36967, 2.91651, 1.6549)
CHROME_K = (5.20655, 4.23131, 3.7547)


def normalise(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def fresnel_conductor(cos_i: np.ndarray, eta, k) -> np.ndarray:
    """Unpolarised Fresnel reflectance (..., C) of a conductor with complex IOR ``eta + i k`` (per channel, C values)
    at incidence cosines ``cos_i`` (...). Same formula as Mitsuba's ``fresnel_conductor``."""
    c = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0)[..., None]
    eta = np.asarray(eta, np.float64)
    k = np.asarray(k, np.float64)
    c2 = c * c
    s2 = 1.0 - c2
    eta2, k2 = eta * eta, k * k
    t0 = eta2 - k2 - s2
    a2pb2 = np.sqrt(t0 * t0 + 4.0 * k2 * eta2)
    a = np.sqrt(np.maximum(0.5 * (a2pb2 + t0), 0.0))
    t1 = a2pb2 + c2
    t2 = 2.0 * c * a
    rs = (t1 - t2) / (t1 + t2)
    t3 = c2 * a2pb2 + s2 * s2
    t4 = t2 * s2
    rp = rs * (t3 - t4) / np.maximum(t3 + t4, 1e-300)
    return 0.5 * (rs + rp)


@dataclass(frozen=True)
class Reflectance:
    """The ball's specular reflectance as a function of the incidence angle.

    ``reflectance``: the calibration factor, reflectance at normal incidence (scalar or RGB). Default 0.65:
    measured chrome balls reflect about 0.6-0.7 at normal incidence (chromium's own Fresnel F0 is 0.69, 0.65,
    0.69 in R, G, B). ``None`` only with ``fresnel="conductor"``: the conductor's own F0.
    ``fresnel``: the angular shape. Reflectance reaches 1 at grazing incidence for any material.
      - ``"conductor"`` (default): the exact conductor Fresnel ``Fc`` of ``eta + i k`` (default chromium's);
        with a ``reflectance`` f0 it is remapped to ``f0 + (1 - f0) (Fc - Fc(0)) / (1 - Fc(0))``: f0 at normal
        incidence, 1 at grazing, chromium's shape between (flat to 40 deg, a dip of ~0.06 near 75 deg, then
        the rise);
      - ``"schlick"``: ``F0 + (1 - F0) (1 - cos i)^5``. Poor for chromium: it has no dip and over-estimates the
        reflectance by 0.04 at 60 deg, 0.14 at 75 deg, 0.19 at 80 deg (up to 30 %);
      - ``"none"``: constant ``reflectance`` (a perfect mirror scaled by it).
    """

    reflectance: float | tuple[float, float, float] | None = 0.65
    fresnel: str = "conductor"
    eta: tuple[float, float, float] = CHROME_ETA
    k: tuple[float, float, float] = CHROME_K

    def __post_init__(self):
        if self.fresnel not in FRESNEL_MODELS:
            raise ValueError(f"fresnel must be one of {FRESNEL_MODELS}, got {self.fresnel!r}")
        if self.reflectance is None and self.fresnel != "conductor":
            raise ValueError("reflectance=None needs fresnel='conductor'")
        if self.reflectance is not None and not np.all(np.asarray(self.reflectance, float) > 0):
            raise ValueError("reflectance must be > 0")

    def f0(self) -> np.ndarray:
        """(3,) reflectance at normal incidence."""
        if self.reflectance is None:
            return fresnel_conductor(np.ones(()), self.eta, self.k)
        return np.broadcast_to(np.asarray(self.reflectance, np.float64), (3,)).copy()

    def __call__(self, cos_i: np.ndarray) -> np.ndarray:
        """Reflectance (..., 3) at incidence cosines (...)."""
        cos_i = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0)
        f0 = self.f0()
        if self.fresnel == "none":
            return np.broadcast_to(f0, cos_i.shape + (3,)).copy()
        if self.fresnel == "schlick":
            return f0 + (1.0 - f0) * ((1.0 - cos_i) ** 5)[..., None]
        f = fresnel_conductor(cos_i, self.eta, self.k)
        if self.reflectance is None:
            return f
        fc0 = fresnel_conductor(np.ones(()), self.eta, self.k)
        return f0 + (1.0 - f0) * (f - fc0) / (1.0 - fc0)

    def to_dict(self) -> dict:
        return {"reflectance": None if self.reflectance is None else np.asarray(self.reflectance).tolist(),
                "fresnel": self.fresnel, "eta": list(self.eta), "k": list(self.k)}


@dataclass
class Reflection:
    """Where the ball shows each direction: per input direction (...)."""

    point: np.ndarray  # (..., 3) world point on the sphere
    normal: np.ndarray  # (..., 3)
    cos_i: np.ndarray  # (...) incidence cosine (n . v)
    converged: np.ndarray = field(default=None)  # (...) bool: the reflection law holds to 1e-6 rad


def reflection_points(d: np.ndarray, centre: np.ndarray, radius: float, eye: np.ndarray,
                      orthographic: bool = False, iterations: int = 8) -> Reflection:
    """The point of the sphere (``centre``, ``radius``) that mirrors direction ``d`` (..., 3 unit) into ``eye``.

    The point lies in the plane through the centre spanned by ``e1`` (centre to eye, distance ``D``) and ``d``.
    With ``d`` at angle ``a`` from ``e1`` in that plane and the normal at angle ``b``, the direction to the eye
    from the point is at ``g(b) = atan2(-R sin b, D - R cos b)`` and the mirror law says ``2 b = a + g(b)``
    (Alhazen's problem): solved by Newton's method from ``b = a / 2``, quadratically convergent (machine
    precision in 3-4 steps, except within a few degrees of straight behind the ball). ``converged``: residual
    below 1e-10 rad. ``orthographic=True``: the textbook shortcut ``b = a / 2`` (camera infinitely far: ``v`` is
    ``e1`` for every point).
    """
    d = np.asarray(d, np.float64)
    c = np.asarray(centre, np.float64)
    o = np.asarray(eye, np.float64)
    e1 = o - c
    dist = float(np.linalg.norm(e1))
    e1 = e1 / dist
    dx, dy, dz = (np.ascontiguousarray(d[..., k]) for k in range(3))
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx / norm, dy / norm, dz / norm
    ca = dx * e1[0] + dy * e1[1] + dz * e1[2]
    px, py, pz = dx - ca * e1[0], dy - ca * e1[1], dz - ca * e1[2]
    sa = np.sqrt(px * px + py * py + pz * pz)
    # e2: d's component perpendicular to e1 (any perpendicular where d is along e1)
    helper = np.array([0.0, 0.0, 1.0]) if abs(e1[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    fallback = np.cross(e1, helper)
    fallback /= np.linalg.norm(fallback)
    tiny = sa < 1e-12
    inv = 1.0 / np.where(tiny, 1.0, sa)
    e2x = np.where(tiny, fallback[0], px * inv)
    e2y = np.where(tiny, fallback[1], py * inv)
    e2z = np.where(tiny, fallback[2], pz * inv)
    alpha = np.arctan2(sa, ca)  # [0, pi]
    beta = 0.5 * alpha
    r = float(radius)
    if orthographic:
        cos_i = np.cos(beta)
        converged = np.ones(beta.shape, bool)
    else:
        for _ in range(iterations):
            cb, sb = np.cos(beta), np.sin(beta)
            x, y = dist - r * cb, -r * sb
            gamma = np.arctan2(y, x)
            f = 2.0 * beta - alpha - gamma
            fp = 2.0 - (r * r - r * dist * cb) / (x * x + y * y)
            beta = beta - f / fp
        cb, sb = np.cos(beta), np.sin(beta)
        gamma = np.arctan2(-r * sb, dist - r * cb)
        converged = np.abs(2.0 * beta - alpha - gamma) < 1e-10
        cos_i = np.cos(beta - gamma)
    cb, sb = np.cos(beta), np.sin(beta)
    n = np.stack([cb * e1[0] + sb * e2x, cb * e1[1] + sb * e2y, cb * e1[2] + sb * e2z], axis=-1)
    return Reflection(c + r * n, n, cos_i, converged & (cos_i > 0))


def cone_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (..., 3) completing ``axis`` (..., 3 unit) to an orthonormal frame."""
    a = np.asarray(axis, np.float64)
    helper = np.where(np.abs(a[..., 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    e1 = normalise(np.cross(a, helper))
    e2 = np.cross(a, e1)
    return e1, e2


def silhouette_rays(centre: np.ndarray, radius: float, eye: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Unit directions (..., K, 3) from ``eye`` of the sphere's tangent cone at angles ``psi`` (K,) about its axis.

    ``centre`` may be (..., 3) for many candidate spheres at once. NaN where the eye is inside the sphere.
    """
    c = np.asarray(centre, np.float64)
    axis = c - np.asarray(eye, np.float64)
    dist = np.linalg.norm(axis, axis=-1, keepdims=True)
    axis = axis / dist
    s = np.where(dist > radius, radius / dist, np.nan)
    alpha = np.arcsin(s)[..., None]  # (..., 1, 1)
    e1, e2 = cone_basis(axis)
    ring = np.cos(psi)[:, None] * e1[..., None, :] + np.sin(psi)[:, None] * e2[..., None, :]
    return np.cos(alpha) * axis[..., None, :] + np.sin(alpha) * ring
