"""Sub-pixel refinement of a chrome ball's centre with a photometric model of its rim (the last step of
:func:`objcam.probe.fit.fit_ball`).

Why a model: a mirror ball's rim is no clean step. At grazing incidence the ball reflects the very ray that
passes it; going inwards, the reflected direction swings away from that ray as the square root of the depth
(``2 sqrt(2 u / r_px)`` rad at ``u`` pixels inside the rim: 7 deg within the first pixel of a 1000 px ball), so
the first pixel inside the rim averages what the environment holds several degrees behind the ball, seen
nowhere else in the photo. An edge detector that looks for "the first step" is pulled inwards by that profile,
by 0.1-0.5 px (courtyard's upper silhouette, 1000 px ball: 0.3-0.5 px), which the plane constraint turns into
a centre error of 0.02-0.05 mm, enough to cost the probe 0.03 of relative RMSE (bench/probe_bench.py).

Model, per arc sector of the rim (``SECTOR_PX`` of arc) and colour channel, in linear radiance at signed
distance ``s`` from the silhouette (pixels, + outwards), ``u = -s`` the depth inside:

    f(s) = b0 + b1 s + c u^p [s < 0]

a locally linear background and, inside, the departure from it: ``p = 0.5`` is the leading term of a smooth
environment (the reflected direction moves as ``sqrt(u)``, and so does the radiance, starting from the
background's own value at the rim); ``p = 0`` is a step (a discontinuity right behind the ball: a texel edge of
a synthetic envmap, or a support near the ball). Each pixel integrates ``f`` over its box (projected on the
edge normal: a trapezoid, in closed form), so the prediction is smooth in the centre. Only pixels near the rim
whose centre lies at most ``inside`` px inside the current silhouette are fitted, ending at 0: then every
fitted pixel is at least half background and the inside enters only through the thin sliver next to the rim,
where one coefficient describes it (deeper lies the environment's texture, squeezed). ``SCHEDULE``: rounds
with ``(inside, p)`` = (0.5, step), (0.25, step), (0, step), then (0, sqrt) until the centre stops moving (at
most ``MAX_EXTRA`` more): the step rounds reach the straddling pixels on every side from a start up to ~1 px
off (a one-sided selection around a wrong centre sees none on one side), the sqrt round removes their inward
bias. For a trial centre the sectors' coefficients are linear: solved exactly (variable projection), residuals
relative to the sector's level per channel; the centre (2 unknowns on the plane, 3 free) minimises the rest
(``scipy.optimize.least_squares``). A sector with no contrast at the rim fits any edge position equally well
and carries no weight by itself; sectors whose RMS exceeds ``OUTLIER`` times the median (a glint, texture
along the arc) are down-weighted by ``(OUTLIER median / rms)^2``.

Measured, centre error from starts 0-0.9 px off (floating 5 cm chromium ball at 35 cm, 25 deg elevation, 16 spp
renders with bracket noise): 1000 px ball 0.001-0.004 mm on forest, courtyard and sunrise (the edge fit:
0.005-0.047 mm); 700 px ball 0.007 mm on courtyard, 0.005 on sunset (edge fit 0.045, 0.006), and 0.03 mm on
courtyard resting on a rendered plane (contact arc skipped; edge fit 0.13 mm). With the contact arc skipped on
the floating 1000 px courtyard ball it did worse (0.076 mm against 0.047): the upper arc's texture is then
balanced by nothing below. At 75-150 px in radius the first pixel spans 13-19 deg of the environment and the
model did no better than the edge fit: :func:`objcam.probe.fit.fit_ball` uses it from 300 px in radius.

The pixel box is the only blur modelled: exact for the synthetic renders (box pixel filter). A real photo's lens
and demosaicing blur spread the edge further; being one-sided, the fit then reads the silhouette as larger by a
fraction of the blur all round, a size change that the plane constraint weighs lightly (the ellipse's position
fixes the centre).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from objcam.camera import Camera
from objcam.probe.silhouette import silhouette_px

SECTOR_PX = 8.0  # arc length of a rim sector (pixels): its coefficients are shared
OUTSIDE_PX = 2.5  # fitted pixels: centre at most this far outside the silhouette
SCHEDULE = ((0.5, 0.0), (0.25, 0.0), (0.0, 0.0), (0.0, 0.5))  # per round: how far inside the silhouette a fitted
# pixel's centre may lie (pixels), and the inside profile's power (0: a step, 0.5: sqrt of the depth)
MAX_EXTRA = 2  # more one-sided rounds while the centre still moves by more than TOL_PX
TOL_PX = 0.05
OUTLIER = 2.5  # sector RMS above this many times the median: weight (OUTLIER median / rms)^2
MIN_PIXELS = 12  # a sector with fewer usable pixels is dropped
MIN_SECTORS = 8  # fewer usable sectors: no refinement


@dataclass
class RimFit:
    centre: np.ndarray  # (3,) world metres
    rms: float  # weighted RMS relative residual of the fitted pixels (fraction of the sector's level)
    n_pixels: int  # pixels fitted in the last round
    n_sectors: int  # sectors fitted in the last round
    coverage: float  # fraction of the rim's sectors fitted (the rest: out of the image, saturated, contact arc)

    def to_dict(self) -> dict:
        return {"centre_world": self.centre.tolist(), "rms": self.rms, "n_pixels": self.n_pixels,
                "n_sectors": self.n_sectors, "coverage": self.coverage}


def _coverage(e: np.ndarray, a: np.ndarray, b: np.ndarray, p: float = 0.0) -> np.ndarray:
    """Mean over a pixel of ``max(t, 0)^p``, ``t`` the depth beyond a straight edge, the pixel's centre at depth
    ``e`` (p = 0: the fraction of the pixel beyond the edge). The unit box projected on the edge normal is
    uniform widths ``a`` = |n_x| and ``b`` = |n_y| convolved (a trapezoid), so the mean is a second difference of
    ``H(t) = max(t, 0)^(p+2) / ((p+1)(p+2))``."""
    k = 1.0 / ((p + 1.0) * (p + 2.0))

    def h(t):
        return k * np.maximum(t, 0.0) ** (p + 2.0)

    sp, sm = 0.5 * (a + b), 0.5 * (a - b)
    return (h(e + sp) - h(e + sm) - h(e - sm) + h(e - sp)) / (a * b)


def _theta(cam: Camera, u: np.ndarray, v: np.ndarray, axis_cam: np.ndarray) -> np.ndarray:
    """Angle (rad) between the rays of pixels (u, v) and the cone axis ``axis_cam`` (camera frame, unit)."""
    q = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.arccos(np.clip(q @ axis_cam, -1.0, 1.0))


def _signed_distance(cam: Camera, u: np.ndarray, v: np.ndarray, centre: np.ndarray,
                     radius: float, pose: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(s, |n_x|, |n_y|), each (N,): signed distance (pixels, + outside) of pixel centres from the image of the
    sphere's silhouette cone and the edge normal's components, to first order in the cone angle (its gradient
    by central differences; the silhouette's curvature over a pixel is negligible). ``pose``: the camera's
    (centre, rotation), precomputed."""
    o, rot = pose if pose is not None else (cam.centre, cam.matrix[:3, :3])
    ax = np.asarray(centre, np.float64) - o
    dist = float(np.linalg.norm(ax))
    axis_cam = rot.T @ (ax / dist)
    alpha = float(np.arcsin(min(radius / dist, 1.0)))
    h = 0.5
    gu = (_theta(cam, u + h, v, axis_cam) - _theta(cam, u - h, v, axis_cam)) / (2 * h)
    gv = (_theta(cam, u, v + h, axis_cam) - _theta(cam, u, v - h, axis_cam)) / (2 * h)
    g = np.maximum(np.hypot(gu, gv), 1e-12)
    return (_theta(cam, u, v, axis_cam) - alpha) / g, np.abs(gu) / g, np.abs(gv) / g


class _Problem:
    """One round: the pixels fitted (fixed while the centre is optimised), their sectors and the residual."""

    def __init__(self, img: np.ndarray, valid: np.ndarray | None, cam: Camera, radius: float, centre: np.ndarray,
                 plane: bool, skip_contact: float, inside_px: float, power: float):
        import cv2

        h, w = img.shape[:2]
        self.cam, self.radius, self.power = cam, radius, power
        self.pose = (cam.centre, cam.matrix[:3, :3])
        f = float(np.sqrt(cam.fx * cam.fy))
        dist = float(np.linalg.norm(centre - cam.centre))
        r_px = self.r_px = f * np.tan(np.arcsin(min(radius / dist, 1.0)))
        ctr = cam.project(centre)
        # candidates: a band drawn along the silhouette polygon, then the exact signed distance
        k_poly = int(np.clip(2 * np.pi * r_px, 64, 8192))
        poly = silhouette_px(cam, np.asarray(centre, np.float64)[None], radius, k_poly)[0]
        mask = np.zeros((h, w), np.uint8)
        half = int(np.ceil(max(OUTSIDE_PX, inside_px))) + 2
        cv2.polylines(mask, [np.round(poly * 4).astype(np.int32)], True, 1, thickness=2 * half + 1, shift=2)
        vv, uu = np.nonzero(mask)
        u, v = uu.astype(np.float64), vv.astype(np.float64)
        s, _, _ = _signed_distance(cam, u, v, centre, radius)
        band = (s >= -inside_px) & (s <= OUTSIDE_PX)
        u, v, s = u[band], v[band], s[band]
        k = max(16, int(round(2 * np.pi * r_px / SECTOR_PX)))
        psi = np.mod(np.arctan2(v - ctr[1], u - ctr[0]), 2 * np.pi)
        sec = np.minimum((psi / (2 * np.pi) * k).astype(int), k - 1)
        drop = np.zeros(k, bool)
        drop[sec[(u <= 0) | (u >= w - 1) | (v <= 0) | (v >= h - 1)]] = True  # cut by the image border
        if plane and skip_contact > 0:  # background rays meeting z = 0 near the contact point: contact shadow
            _, d = cam.rays(u, v)
            o = cam.centre
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -o[2] / d[:, 2]
            q = o + t[:, None] * d
            hit = (t > 0) & (s > 0) & (np.hypot(q[:, 0] - centre[0], q[:, 1] - centre[1]) < skip_contact * radius)
            drop[sec[hit]] = True
        ok = ~drop[sec]
        if valid is not None:
            ok &= np.asarray(valid, bool)[v.astype(int), u.astype(int)]
        ok &= np.bincount(sec[ok], minlength=k)[sec] >= MIN_PIXELS
        self.u, self.v = u[ok], v[ok]
        used, self.sec = np.unique(sec[ok], return_inverse=True)
        self.n_sec = len(used)
        self.coverage = self.n_sec / k
        self.y = np.asarray(img, np.float64)[self.v.astype(int), self.u.astype(int), :3]  # (N, 3)
        # relative residuals: the envmap's range and shot noise make absolute ones incomparable around the rim
        floor = 1e-3 * max(float(np.median(np.abs(self.y))) if self.y.size else 0.0, 1e-30)
        self.scale = np.stack([np.maximum(_group_median(np.abs(self.y[:, c]), self.sec, self.n_sec), floor)
                               for c in range(3)], -1) if self.n_sec else np.ones((0, 3))
        self.sector_w = np.ones(self.n_sec)

    def residual(self, centre: np.ndarray) -> np.ndarray:
        """(N * 3,) weighted relative residuals of the rim model with each sector's coefficients solved."""
        s, a, b = _signed_distance(self.cam, self.u, self.v, centre, self.radius, self.pose)
        a, b = np.maximum(a, 1e-3), np.maximum(b, 1e-3)
        A = np.stack([np.ones_like(s), s, _coverage(-s, a, b, self.power)], -1)
        sw = (self.sector_w[self.sec][:, None] / self.scale[self.sec]) ** 2  # (N, 3) weights
        pred = np.empty_like(self.y)
        npar = A.shape[1]
        for c in range(3):
            w = sw[:, c]
            AtA = np.empty((self.n_sec, npar, npar))
            for i in range(npar):
                for j in range(i, npar):
                    AtA[:, i, j] = AtA[:, j, i] = np.bincount(self.sec, w * A[:, i] * A[:, j], self.n_sec)
            Aty = np.stack([np.bincount(self.sec, w * A[:, i] * self.y[:, c], self.n_sec) for i in range(npar)], -1)
            ridge = 1e-9 * np.trace(AtA, axis1=1, axis2=2)[:, None, None] * np.eye(npar)
            coef = np.linalg.solve(AtA + ridge, Aty[..., None])[..., 0]  # (S, P)
            pred[:, c] = np.sum(A * coef[self.sec], axis=1)
        return ((self.y - pred) * np.sqrt(sw)).ravel()

    def sector_rms(self, centre: np.ndarray) -> np.ndarray:
        """(S,) RMS relative residual per sector, before the sector weights."""
        r = self.residual(centre).reshape(-1, 3) / np.maximum(self.sector_w[self.sec], 1e-12)[:, None]
        n = 3 * np.bincount(self.sec, minlength=self.n_sec)
        return np.sqrt(np.bincount(self.sec, (r ** 2).sum(axis=1), self.n_sec) / np.maximum(n, 1))


def _group_median(x: np.ndarray, g: np.ndarray, n: int) -> np.ndarray:
    """(n,) median of ``x`` over each group id in ``g`` (every id in 0..n-1 present)."""
    order = np.lexsort((x, g))
    xs, gs = x[order], g[order]
    starts = np.searchsorted(gs, np.arange(n))
    ends = np.searchsorted(gs, np.arange(n), side="right")
    mid = 0.5 * (starts + ends - 1)
    return 0.5 * (xs[np.floor(mid).astype(int)] + xs[np.ceil(mid).astype(int)])


def refine_rim(img: np.ndarray, valid: np.ndarray | None, cam: Camera, radius: float, centre0,
               plane: bool = True, skip_contact: float = 0.0) -> RimFit | None:
    """The centre (world metres) whose rim model best explains ``img`` (H, W, 3) linear radiance, from
    ``centre0`` (within ~1 px of the truth: the edge fit's result). ``valid`` (H, W) bool: False where the
    pixel is saturated in every frame (not fitted). ``plane``: z stays at ``centre0``'s (x, y free), else x, y,
    z free. ``skip_contact``: with ``plane``, leave out the sectors whose background meets z = 0 within this
    many radii of the contact point. None when fewer than ``MIN_SECTORS`` sectors are usable."""
    from scipy.optimize import least_squares

    from objcam.threads import single_blas_thread

    centre = np.asarray(centre0, np.float64).copy()
    prob = None
    extra = 0
    with single_blas_thread():
        rounds = list(SCHEDULE)
        while rounds:
            inside, power = rounds.pop(0)
            prob = _Problem(img, valid, cam, radius, centre, plane, skip_contact, inside, power)
            if prob.n_sec < MIN_SECTORS:
                return None
            rms = prob.sector_rms(centre)
            x = rms / max(OUTLIER * float(np.median(rms)), 1e-300)
            prob.sector_w = np.where(x <= 1.0, 1.0, 1.0 / np.maximum(x, 1e-300) ** 2)
            # unknowns: the centre's offset from this round's start in pixels at the ball (x, y[, z])
            start = centre.copy()
            m_px = radius / max(prob.r_px, 1e-9)

            def at(p, start=start):
                c = start.copy()
                c[:len(p)] += m_px * p
                return c

            def fun(p, prob=prob, at=at):
                return prob.residual(at(p))

            # 2-point differences of 0.05 px: the model is smooth in the centre at that scale
            # (tolerances: 1e-4 px on the centre is plenty; the defaults spend ~35 evaluations a round)
            sol = least_squares(fun, np.zeros(2 if plane else 3), diff_step=0.05, method="trf", xtol=1e-4,
                                ftol=1e-6)
            centre = at(sol.x)
            extra += not rounds
            if not rounds and np.linalg.norm(sol.x) > TOL_PX and extra <= MAX_EXTRA:
                rounds.append(SCHEDULE[-1])  # the one-sided fit is still moving: another round at its centre
        r = prob.residual(centre)
    return RimFit(centre, float(np.sqrt(np.mean(r ** 2))), len(prob.u), prob.n_sec, float(prob.coverage))
