"""Find a chrome ball of known radius in a merged HDR image seen by a known (OpenCV pinhole) camera, and fit its
3D centre to the silhouette with sub-pixel accuracy.

A sphere's silhouette is the cone from the camera centre ``O`` tangent to it: axis towards the centre ``C``,
half-angle ``asin(R / |C - O|)``; its image is an ellipse when off-axis. Everything works on that cone in the
world frame, so perspective is exact.

1. Detection, on a copy shrunk to ~400 px (log-luminance, Gaussian sigma 1 px). Each candidate silhouette (64
   points) is scored by its edge support in [0, 1]: per point the mean of the log-luminance step across the
   silhouette, ``min(|dL/dn| / tau, 1)`` (``tau``: the image's 90th-percentile gradient), and the texture
   asymmetry ``clip((G_in - G_out) / (G_in + G_out), 0, 1)`` of the gradient magnitude 1-3 px inside vs outside
   (a ball minifies what it reflects, so it is busier than the background beside it); averaged over the points
   inside the image and multiplied by ``min(1, inside fraction / 0.9)``.
   - ``rests_on_plane``: each image position of the centre fixes the 3D centre (its ray meets z = radius), hence
     the silhouette: brute force every 2 px, the best peaks polished by pattern search.
   - free: OpenCV ``HoughCircles`` proposals (on the log-luminance and on the texture energy), each turned into a
     sphere (distance from the apparent radius), polished in (u, v, r). Less reliable: a textured background
     offers ball-like circles of any size; give ``approx_px`` or ``known_centre`` when it fails.
   - the ball must score >= ``MIN_SUPPORT``; a disjoint second candidate within ``TWIN_RATIO`` of the best is a
     second ball; a best candidate (or, failing any, a strong partial one) whose silhouette leaves the image is a
     ball cut by the edge. Each is an InputError naming the image.
2. Refinement, coarse to fine (factors 2^k of the detection scale down to full resolution): edge points along
   the normals of the current silhouette (~1 px apart). A mirror ball's rim is continuous with the background
   (at grazing incidence it reflects the very ray that passes it, with reflectance -> 1), so the edge is where
   the image stops being smooth background: scanning inwards, the first sample where any channel's log
   radiance departs from the background level (median over 1 px and more outside) by > ``DEPART_LOG`` (or 4x
   the background noise) for ``SUSTAIN`` px; then the half-height point, in linear radiance, of that first
   step (box-filtered pixels put a step's half-height point on the geometric edge whatever its size). Then a
   robust (soft-L1, 0.5 px) least-squares fit of the cone to the edge rays, residual = angle between edge ray
   and cone axis minus the half-angle, x focal length (pixels). Four rounds, windows 3, 2, 1.5, 1.5 px.
   - ``rests_on_plane``: unknowns (x, y) of the centre, z = radius; the distance comes from the plane more than
     from the apparent size. Silhouette points whose background is the support within ``CONTACT_SKIP`` radii
     of the contact point (contact shadow) are left out. ``edge_bias_px`` (median residual) checks the size: a
     silhouette more than max(2 px, 3 % of the radius) off the predicted one is warned about (wrong diameter,
     ball not on the plane).
   - free: the three coordinates: the depth hangs on the apparent size (4.7 mm per pixel of radius for a 5 cm
     ball spanning 150 px at 35 cm), and the detection is less reliable (see above).
   - ``known_centre`` (e.g. the board's pose plus the radius): used as given; ``residual_px`` and
     ``edge_bias_px`` measure the edges against it, and a fit at its height (x, y free, steps 3-4 below)
     reports ``fitted_offset_mm``, warned about beyond ``KNOWN_TOLERANCE_MM``.
3. Contact arc (plane mode, ``contact_arc="auto"``): the arc skipped above is measured at the fitted centre;
   when its edges agree with the rest (``_contact_arc_agrees``: found, no offset, little spread: a floating
   ball, or a contact shadow that leaves the edge clean) the fit is redone with the whole silhouette
   (``"fit"``: always; ``"skip"``: never). The arc is a third of the rim at 25 deg elevation, and it is the arc
   that balances the upper one: on the benchmark's floating balls fitting it took courtyard's edge-fit error
   from 0.047 to 0.024 mm; resting on a rendered diffuse plane (1000 px ball) it still helped (courtyard
   0.070 -> 0.028 mm, forest 0.055 -> 0.046 mm, edge fit).
4. Rim model (:mod:`objcam.probe.rim`, balls of ``RIM_MIN_RADIUS_PX`` or more): a photometric model of the pixels
   straddling the rim replaces the edge points' "first step", which a mirror ball's rim texture biases by
   0.1-0.5 px; kept when it moves the silhouette by at most ``RIM_MAX_SHIFT_PX``. ``BallFit.edge_centre_world``
   keeps the edge fit, ``BallFit.rim`` the record.

Measured on the issue's benchmark (bench/probe_bench.py: 1400 px image, ball 1000 px, 16 spp, bracket noise,
floating ball): centre error 0.001-0.004 mm (forest, courtyard, sunrise) against 0.010-0.047 mm for the edge
fit with the contact arc skipped; the probe's relative RMSE follows (courtyard 0.055 -> 0.021, as with the true
centre). Resting on a rendered plane: 0.02-0.05 mm (forest, courtyard). The rim model leans on the contact arc:
with it skipped (``contact_arc="skip"``) the floating courtyard ball got 0.076 mm (edge fit 0.047), the others
0.002-0.006. At 75-150 px radius the rim model did no better than the edge fit (0.05-0.08 mm against
0.05-0.08), hence the size limit.

Measured before steps 3-4 on synthetic 256 px brackets (5 cm chrome or mirror ball spanning 150 px at 35 cm;
forest, sunrise, city, courtyard, sunset; up to 50 px off-axis; 15-45 deg elevation), refinement started 1.4 mm
off, plane mode: floating ball (24 scenes) centre error rms 0.13 mm, max 0.26 mm (~0.8 px), residual ~0.3 px;
resting on a rendered diffuse plane (6 scenes, contact shadow, 256 spp) rms 0.38 mm, max 0.87 mm. Free mode: rms
1.2-2.5 mm, max 5 mm. At 1024 px (ball 600 px): plane mode 0.01-0.11 mm (on a rendered plane), 0.02-0.03 mm
floating; at 2048 px (1200 px) 0.004-0.012 mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.errors import InputError
from objcam.probe.optics import normalise, silhouette_rays
from objcam.probe.rim import refine_rim
from objcam.probe.silhouette import silhouette_px

LUMA = np.array([0.2126, 0.7152, 0.0722])
MIN_SUPPORT = 0.46  # edge support a silhouette needs to count as a ball
CUT_MARGIN = 0.04  # a candidate cut by the image edge needs this much more support (over its visible part)
TWIN_RATIO = 0.75  # a disjoint second candidate this close to the best support is a second ball
TWIN_RATIO_FREE = 0.85  # ... without the plane constraint (and of a similar apparent size)
DETECT_SIZE = 400  # detection runs on a copy whose smaller side is at most about this many pixels
DEPART_LOG = 0.08  # log-radiance departure from the background that marks the silhouette
MAX_EDGE_BIAS_PX = 2.0
WINDOWS = (3.0, 2.0, 1.5, 1.5)
SUSTAIN = 0.25  # pixels a departure must last inwards (noise and background texture make spikes)
HALF_SCAN = 1.0  # pixels scanned inwards from the departure for the step's first peak
CONTACT_SKIP = 1.0  # plane mode ignores silhouette points whose background meets z = 0 this many radii from
# the contact point
MIN_RADIUS_PX = 30.0  # smallest apparent ball radius searched for (full-resolution pixels)
ARC_FOUND, ARC_INLIERS, ARC_SPREAD_PX, ARC_BIAS_PX = 0.8, 0.85, 0.5, 0.25  # a contact arc this clean is fitted
# (_contact_arc_agrees)
RIM_MAX_SHIFT_PX = 1.0  # the rim model may move the edge fit's silhouette by at most this much
RIM_MIN_RADIUS_PX = 300.0  # smaller balls keep the edge fit (their first pixel inside the rim spans too many
# degrees of the environment for the rim model's one level: measured worse at 150 px, see objcam/probe/rim.py)
KNOWN_TOLERANCE_MM = 0.5  # a known centre this far from where the photo puts the ball is warned about

SHOOT_BALL = ("photograph the chrome ball whole, inside the frame with a margin, spanning >= 150 px (60 px at "
              "least), against a background that differs from its rim")


@dataclass
class BallFit:
    """A fitted chrome ball."""

    centre_world: np.ndarray  # (3,) metres
    radius: float  # metres (the given one)
    residual_px: float  # RMS distance of inlier edge points from the fitted silhouette, pixels
    centre_px: np.ndarray  # (2,) projection of the centre (u, v)
    apparent_radius_px: float  # f * tan(half-angle of the silhouette cone)
    edge_bias_px: float = 0.0  # median edge offset from the fitted silhouette (pixels, + = outside): a size check
    support: float = 0.0  # detection edge support in [0, 1]
    n_edges: int = 0  # edge points used in the last iteration
    inlier_fraction: float = 0.0  # of edge points within 1.5 px of the silhouette
    mode: str = "plane"  # "plane", "free" or "known"
    warnings: list[str] = field(default_factory=list)
    contact_arc: str = "n/a"  # plane mode: "fitted" (its edges agreed with the rest, or forced) or "skipped"
    edge_centre_world: np.ndarray | None = None  # (3,) the edge fit's centre, before the rim model
    rim: dict | None = None  # the rim model's refinement (objcam.probe.rim.RimFit.to_dict + "used", "shift_px")
    fitted_offset_mm: float | None = None  # known mode: distance from the known centre to the plane-style fit

    def to_dict(self) -> dict:
        return {"centre_world": self.centre_world.tolist(), "radius": self.radius, "residual_px": self.residual_px,
                "centre_px": self.centre_px.tolist(), "apparent_radius_px": self.apparent_radius_px,
                "edge_bias_px": self.edge_bias_px, "support": self.support, "n_edges": self.n_edges,
                "inlier_fraction": self.inlier_fraction, "mode": self.mode, "warnings": list(self.warnings),
                "contact_arc": self.contact_arc,
                "edge_centre_world": None if self.edge_centre_world is None else self.edge_centre_world.tolist(),
                "rim": self.rim, "fitted_offset_mm": self.fitted_offset_mm}


# ------------------------------------------------------------------------------------------------ images


def log_luminance(hdr: np.ndarray) -> np.ndarray:
    """(H, W) float32 log of the luminance with a floor at 1e-3 of the median positive luminance."""
    hdr = np.asarray(hdr, np.float32)
    lum = hdr[..., :3] @ LUMA.astype(np.float32) if hdr.ndim == 3 else hdr
    pos = lum[lum > 0]
    floor = 1e-3 * float(np.median(pos)) if pos.size else 1e-30
    return np.log(np.maximum(lum, 0) + max(floor, 1e-30)).astype(np.float32)


def _smooth(img: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of a 2D image at continuous pixel positions (OpenCV centres), edge-clamped."""
    from scipy.ndimage import map_coordinates

    return map_coordinates(img, [np.ravel(v), np.ravel(u)], order=1, mode="nearest").reshape(np.shape(u))


def _sample_fast(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples via cv2.remap (coordinates quantised to 1/32 px; for detection), edge-clamped."""
    import cv2

    shape = np.shape(u)
    uu = np.ravel(u).astype(np.float32)
    vv = np.ravel(v).astype(np.float32)
    n = uu.size
    cols = 1024
    rows = -(-n // cols)
    pad = rows * cols - n
    mu = np.pad(uu, (0, pad)).reshape(rows, cols)
    mv = np.pad(vv, (0, pad)).reshape(rows, cols)
    out = cv2.remap(np.ascontiguousarray(img, np.float32), mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].reshape(shape)


def _scaled_camera(cam: Camera, w: int, h: int) -> Camera:
    """The camera of the image resized to ``w`` x ``h`` (OpenCV centres: x' = (x + 0.5) w / W - 0.5, as
    cv2.resize maps pixels)."""
    sx, sy = w / cam.width, h / cam.height
    return Camera(width=w, height=h, fx=cam.fx * sx, fy=cam.fy * sy, cx=(cam.cx + 0.5) * sx - 0.5,
                  cy=(cam.cy + 0.5) * sy - 0.5, world_from_camera=cam.world_from_camera)


def _shrink(img: np.ndarray, cam: Camera, s: float) -> tuple[np.ndarray, Camera]:
    """``img`` area-averaged down by about ``s`` (>= 1) and its camera."""
    import cv2

    if s <= 1.0:
        return img, cam
    w, h = max(int(round(cam.width / s)), 1), max(int(round(cam.height / s)), 1)
    small = cv2.resize(np.ascontiguousarray(img, np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return small, _scaled_camera(cam, w, h)


def _pixel_rays(cam: Camera, pts: np.ndarray) -> np.ndarray:
    _, d = cam.rays(pts[..., 0], pts[..., 1])
    return d


def _focal(cam: Camera) -> float:
    return float(np.sqrt(cam.fx * cam.fy))


# ----------------------------------------------------------------------------------------- silhouettes


def _support(gx: np.ndarray, gy: np.ndarray, tau: float, pts: np.ndarray, ctr: np.ndarray,
             shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Edge support (...,) in [0, 1] of silhouettes ``pts`` (..., k, 2) around image centres ``ctr`` (..., 2),
    and the fraction of their points inside the image.

    Per silhouette point, the mean of two cues: the log-luminance step across the silhouette,
    ``min(|dL/dn| / tau, 1)``, and the texture asymmetry ``clip((G_in - G_out) / (G_in + G_out), 0, 1)`` of the
    gradient magnitude G summed 1, 2, 3 px inside and outside (a ball minifies what it reflects, so it is busier
    than the background next to it). Averaged over the points inside the image.
    """
    h, w = shape
    u, v = pts[..., 0], pts[..., 1]
    finite = np.isfinite(u) & np.isfinite(v)
    inside = finite & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    uu, vv = np.where(finite, u, 0), np.where(finite, v, 0)
    n = normalise(np.stack([uu - ctr[..., None, 0], vv - ctr[..., None, 1]], -1))
    g = _sample_fast(gx, uu, vv) * n[..., 0] + _sample_fast(gy, uu, vv) * n[..., 1]
    step = np.minimum(np.abs(g) / tau, 1.0)
    mag = np.hypot(gx, gy)
    e_in = sum(_sample_fast(mag, uu - d * n[..., 0], vv - d * n[..., 1]) for d in (1.0, 2.0, 3.0))
    e_out = sum(_sample_fast(mag, uu + d * n[..., 0], vv + d * n[..., 1]) for d in (1.0, 2.0, 3.0))
    tex = np.clip((e_in - e_out) / (e_in + e_out + 1e-6 * tau), 0.0, 1.0)
    s = 0.5 * (step + tex)
    frac = inside.mean(axis=-1)
    sup = np.where(inside, s, 0).sum(axis=-1) / np.maximum(inside.sum(axis=-1), 1)
    return sup, frac


def _plane_centres(cam: Camera, pts: np.ndarray, radius: float) -> np.ndarray:
    """3D centres (..., 3) on z = radius along the rays of pixels ``pts`` (..., 2); NaN where the ray misses."""
    d = _pixel_rays(cam, pts)
    o = cam.centre
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (radius - o[2]) / d[..., 2]
    t = np.where((t > 0) & np.isfinite(t), t, np.nan)
    c = o + t[..., None] * d
    dist = np.linalg.norm(c - o, axis=-1)
    return np.where((dist > 1.5 * radius)[..., None], c, np.nan)


@dataclass
class _Candidate:
    params: np.ndarray  # (u, v) on the plane, (u, v, r_px) free; detection-image pixels
    centre: np.ndarray  # world
    support: float  # edge support over the in-image points, times min(1, inside / 0.9)
    raw: float  # edge support over the in-image points
    inside: float  # fraction of the silhouette inside the image
    ctr_px: np.ndarray  # projection of the centre (detection pixels until fit_ball rescales)
    r_px: float


def _centres_of(cam: Camera, params: np.ndarray, radius: float, plane: bool) -> np.ndarray:
    """3D centres (N, 3) for candidate parameters (N, 2) (plane: pixel of the centre) or (N, 3) (free: pixel
    and apparent radius in pixels)."""
    if plane:
        return _plane_centres(cam, params[:, :2], radius)
    d = _pixel_rays(cam, params[:, :2])
    alpha = np.arctan(np.maximum(params[:, 2], 1e-3) / _focal(cam))
    return cam.centre + (radius / np.sin(alpha))[:, None] * d


def _score(cam: Camera, gx, gy, tau, radius: float, centres: np.ndarray):
    """(penalised support, raw support, inside fraction), each (N,), of spheres at ``centres`` (N, 3)."""
    ok = np.all(np.isfinite(centres), axis=1)
    sup = np.zeros(len(centres))
    raw = np.zeros(len(centres))
    frac = np.zeros(len(centres))
    idx = np.flatnonzero(ok)
    for chunk in np.array_split(idx, max(1, len(idx) // 4096)):
        if not len(chunk):
            continue
        c = centres[chunk]
        pts = silhouette_px(cam, c, radius, 64)
        s, f = _support(gx, gy, tau, pts, cam.project(c), gx.shape)
        raw[chunk] = np.where(f >= 0.3, s, 0.0)
        sup[chunk] = raw[chunk] * np.minimum(1.0, f / 0.9)
        frac[chunk] = f
    return sup, raw, frac


def _polish(cam: Camera, gx, gy, tau, radius: float, cand: _Candidate, plane: bool, min_r: float,
            step: float = 4.0) -> _Candidate:
    """Pattern search on the candidate's parameters (steps of 4 px, halved down to 1/4 px) maximising support."""
    p = cand.params.astype(np.float64).copy()
    best = cand.support
    dim = 2 if plane else 3
    offs = np.array(np.meshgrid(*[[-1.0, 0.0, 1.0]] * dim, indexing="ij")).reshape(dim, -1).T
    while step >= 0.25:
        trial = p + step * offs
        if not plane:
            trial[:, 2] = np.maximum(trial[:, 2], min_r)
        sup, _, _ = _score(cam, gx, gy, tau, radius, _centres_of(cam, trial, radius, plane))
        i = int(np.argmax(sup))
        if sup[i] > best + 1e-9:
            best, p = float(sup[i]), trial[i]
        else:
            step /= 2
    c = _centres_of(cam, p[None], radius, plane)[0]
    sup, raw, frac = _score(cam, gx, gy, tau, radius, c[None])
    r_px = _focal(cam) * np.tan(np.arcsin(min(radius / np.linalg.norm(c - cam.centre), 1.0)))
    return _Candidate(p, c, float(sup[0]), float(raw[0]), float(frac[0]), cam.project(c), float(r_px))


def _same(a: _Candidate, b: _Candidate) -> bool:
    """Two candidates for one ball: centres within half the mean radius and radii within a factor 1.5."""
    return bool(np.linalg.norm(a.ctr_px - b.ctr_px) < 0.25 * (a.r_px + b.r_px)
                and max(a.r_px, b.r_px) < 1.5 * min(a.r_px, b.r_px))


def _disjoint(a: _Candidate, b: _Candidate) -> bool:
    """The two silhouettes (nearly) do not overlap."""
    return bool(np.linalg.norm(a.ctr_px - b.ctr_px) >= 0.9 * (a.r_px + b.r_px))


def _distinct(cands: list[_Candidate], limit: int = 5) -> list[_Candidate]:
    """Best first, dropping candidates for the same ball as a better one."""
    out: list[_Candidate] = []
    for c in sorted(cands, key=lambda c: -c.support):
        if any(_same(c, o) for o in out):
            continue
        out.append(c)
        if len(out) >= limit:
            break
    return out


def _candidates_plane(cam: Camera, gx, gy, tau, radius: float, min_r: float, step: float = 2.0) -> list[_Candidate]:
    """Brute force over centre pixels every ``step`` px, the 8 best distinct peaks polished."""
    from scipy.ndimage import maximum_filter

    h, w = gx.shape
    uu, vv = np.meshgrid(np.arange(0, w, step, dtype=np.float64), np.arange(0, h, step, dtype=np.float64))
    grid = np.stack([uu.ravel(), vv.ravel()], -1)
    centres = _plane_centres(cam, grid, radius)
    ok = np.all(np.isfinite(centres), axis=-1)
    dist = np.linalg.norm(np.where(ok[:, None], centres, 0) - cam.centre, axis=-1)
    rpx = np.zeros(len(grid))
    rpx[ok] = _focal(cam) * np.tan(np.arcsin(np.clip(radius / dist[ok], 0, 1)))
    centres[~(ok & (rpx >= min_r) & (rpx <= max(h, w)))] = np.nan
    sup, raw, frac = _score(cam, gx, gy, tau, radius, centres)
    smap = sup.reshape(uu.shape)
    peak = (smap == maximum_filter(smap, size=5, mode="nearest")) & (smap > 0.15)
    ii = np.flatnonzero(peak.ravel())
    cands = [_Candidate(grid[i], centres[i], float(sup[i]), float(raw[i]), float(frac[i]), grid[i], float(rpx[i]))
             for i in ii]
    cands = _distinct(cands, 8)
    return _distinct([_polish(cam, gx, gy, tau, radius, c, True, min_r) for c in cands])


def _candidates_free(cam: Camera, logl: np.ndarray, gx, gy, tau, radius: float, min_r: float) -> list[_Candidate]:
    """OpenCV Hough circles (HOUGH_GRADIENT_ALT) on the smoothed log-luminance and on its smoothed gradient
    magnitude (texture energy: a ball is busier than its background), as spheres; the 8 best distinct by support
    polished, best first."""
    import cv2

    h, w = logl.shape
    props = []
    for img in (logl, _smooth(np.hypot(gx, gy), 2.0)):
        lo, hi = np.percentile(img, [1, 99.5])
        img8 = np.clip((img - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
        circles = cv2.HoughCircles(img8, cv2.HOUGH_GRADIENT_ALT, dp=1.5, minDist=8, param1=60, param2=0.5,
                                   minRadius=int(max(4, min_r)), maxRadius=int(max(h, w) / 2))
        if circles is not None:
            props.append(circles.reshape(-1, 3)[:20].astype(np.float64))
    if not props:
        return []
    params = np.concatenate(props)
    centres = _centres_of(cam, params, radius, False)
    sup, raw, frac = _score(cam, gx, gy, tau, radius, centres)
    cands = [_Candidate(params[i], centres[i], float(sup[i]), float(raw[i]), float(frac[i]), params[i, :2],
                        float(params[i, 2])) for i in range(len(params)) if frac[i] >= 0.3]
    cands = _distinct(cands, 12)
    return _distinct([_polish(cam, gx, gy, tau, radius, c, False, min_r) for c in cands])


# ------------------------------------------------------------------------------------------- refinement


def log_rgb(hdr: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 per-channel log radiance with a floor at 1e-3 of the median positive value."""
    hdr = np.asarray(hdr, np.float32)[..., :3]
    pos = hdr[hdr > 0]
    floor = 1e-3 * float(np.median(pos)) if pos.size else 1e-30
    return np.log(np.maximum(hdr, 0) + max(floor, 1e-30)).astype(np.float32)


def _contact_arc(cam: Camera, rays: np.ndarray, centre: np.ndarray, radius: float, skip: float) -> np.ndarray:
    """(K,) bool: silhouette rays ``rays`` (K, 3) whose background is the support next to the contact point
    (the contact shadow): they pass the ball and meet z = 0 within ``skip`` radii of the point below its
    centre."""
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = -cam.centre[2] / rays[:, 2]
    q = cam.centre + tp[:, None] * rays
    return (tp > 0) & (np.hypot(q[:, 0] - centre[0], q[:, 1] - centre[1]) < skip * radius)


def _edge_points(logc: np.ndarray, cam: Camera, centre: np.ndarray, radius: float, alpha_offset: float,
                 window: float, skip_contact: float = 0.0,
                 contact_only: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Silhouette edge positions (N, 2) along the outward normals of the model silhouette, their departure
    strengths (N,) and the fraction of silhouette points inside the image.

    Per normal profile of the per-channel log image ``logc`` (t from -window to +window pixels, outwards,
    1/8 px steps): the background level is the median over t >= 1 px; scanning inwards, the first sample where
    any channel departs from it by more than ``DEPART_LOG`` (or 4x the background noise) marks the ball; the
    edge is then the half-height point, in linear radiance, of that channel's first step (its deviation's first
    peak within ``HALF_SCAN`` px further in): the box-filtered pixels and bilinear sampling make a step's
    half-height point sit on the geometric edge whatever the step's size, where a fixed threshold moves with
    it. A mirror ball's rim is continuous with the background (at grazing incidence it reflects the very ray
    that passes it, with reflectance -> 1), so the step is the Fresnel dip just inside the rim and the
    compressed reflection's texture, and its size varies around the rim.
    """
    h, w = logc.shape[:2]
    dist = np.linalg.norm(centre - cam.centre)
    alpha = np.arcsin(min(radius / dist, 1.0)) + alpha_offset
    r_px = _focal(cam) * np.tan(alpha)
    k = int(np.clip(2 * np.pi * r_px, 64, 4096))
    psi = 2 * np.pi * np.arange(k) / k
    rays = silhouette_rays(cam.centre + (centre - cam.centre) / dist, np.sin(alpha), cam.centre, psi)
    pts = cam.project(cam.centre + rays)
    tang = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    nrm = normalise(np.stack([tang[:, 1], -tang[:, 0]], -1))
    ctr = cam.project(centre)
    flip = np.sum(nrm * (pts - ctr), axis=-1) < 0
    nrm[flip] *= -1
    inside = (pts[:, 0] >= window + 1) & (pts[:, 0] <= w - 2 - window) & (pts[:, 1] >= window + 1) & \
             (pts[:, 1] <= h - 2 - window)
    frac = float(inside.mean())
    if skip_contact > 0:
        near = _contact_arc(cam, rays, centre, radius, skip_contact)
        inside = inside & (near if contact_only else ~near)
    pts, nrm = pts[inside], nrm[inside]
    step = 0.125
    t = np.arange(-window, max(window, 1.5) + 1e-9, step)
    pu, pv = pts[:, None, 0] + t * nrm[:, None, 0], pts[:, None, 1] + t * nrm[:, None, 1]
    chans = logc[..., None] if logc.ndim == 2 else logc
    prof = np.stack([_sample(chans[..., q], pu, pv) for q in range(chans.shape[2])], 0)  # (C, N, T)
    outer = t >= 1.0
    bg = np.median(prof[:, :, outer], axis=2, keepdims=True)
    dev = np.abs(prof - bg).max(axis=0)  # (N, T)
    noise = 1.4826 * float(np.median(np.abs(prof[:, :, outer] - bg)))
    thr = max(DEPART_LOG, 4.0 * noise)
    inner = np.flatnonzero(~outer)
    over = dev[:, inner] > thr
    m = int(round(SUSTAIN / step))  # a departure must hold for SUSTAIN px inwards (not a noise spike)
    if m > 0:
        run = np.ones_like(over)
        for q in range(1, m + 1):
            run[:, q:] &= over[:, :-q]
        run[:, :m] = False
        over = run  # over[i] now: samples i - m .. i all departed; report the outermost (i)
    has = over.any(axis=1)
    j = inner[-1] - np.argmax(over[:, ::-1], axis=1)  # outermost departed sample below t = 1
    n = np.arange(len(j))
    tt = t[j].copy()
    ok = has & (j > 0)
    # refine to the half-height point of the first step inwards (linear radiance)
    lin = np.exp(prof - bg) - 1.0  # relative linear deviation from the background, (C, N, T)
    cstar = np.argmax(np.abs(lin[:, n, j]), axis=0)
    sgn = np.sign(lin[cstar, n, j])
    prof1 = sgn[:, None] * lin[cstar, n, :]  # (N, T), positive inside the departure
    peak = j.copy()
    scan = int(round(HALF_SCAN / step))
    lim = np.maximum(j - scan, 0)
    for _ in range(scan):
        up = (peak - 1 >= lim) & (prof1[n, np.maximum(peak - 1, 0)] >= prof1[n, peak])
        peak = np.where(up, peak - 1, peak)
    half = 0.5 * prof1[n, peak]
    # the first crossing of half outwards from the peak
    tt2 = t[peak].copy()
    done = np.zeros(len(peak), bool)
    for q in range(scan + int(round(2.0 / step))):
        a_i = np.minimum(peak + q, len(t) - 2)
        ya, yb = prof1[n, a_i], prof1[n, a_i + 1]
        cross = ~done & (ya >= half) & (yb < half)
        fr = np.where(cross, (ya - half) / np.maximum(ya - yb, 1e-12), 0.0)
        tt2 = np.where(cross, t[a_i] + fr * step, tt2)
        done |= cross
    tt = np.where(done, tt2, tt)
    strength = dev[:, inner].max(axis=1)
    edge = pts + tt[:, None] * nrm
    return edge[ok], strength[ok], frac


def _cone_residuals(rays: np.ndarray, o: np.ndarray, centre: np.ndarray, radius: float, beta: float,
                    f: float) -> np.ndarray:
    ax = centre - o
    dist = np.linalg.norm(ax)
    ax = ax / dist
    ang = np.arctan2(np.linalg.norm(np.cross(rays, ax), axis=-1), rays @ ax)
    return f * (ang - np.arcsin(np.clip(radius / dist, 0, 1)) - beta)


def _refine(logc, cam: Camera, radius: float, centre0: np.ndarray, mode: str, source,
            windows=WINDOWS, skip_contact: float = CONTACT_SKIP) -> BallFit:
    from scipy.optimize import least_squares

    f = _focal(cam)
    o = cam.centre
    centre = np.asarray(centre0, np.float64).copy()
    res = None
    frac = 1.0
    for win in windows:
        edge, strength, frac = _edge_points(logc, cam, centre, radius, 0.0, win,
                                            skip_contact if mode == "plane" else 0.0)
        if frac < 0.98:
            break
        if len(edge) < 16:
            break
        rays = _pixel_rays(cam, edge)
        if mode == "known":
            res = _cone_residuals(rays, o, centre, radius, 0.0, f)
            continue
        if mode == "plane":
            x0 = np.array([centre[0], centre[1]])
            sc = np.array([radius, radius])
            z = centre[2]  # radius for a ball on the plane; a known centre's own height when checking it

            def fun(p, z=z):
                return _cone_residuals(rays, o, np.array([p[0], p[1], z]), radius, 0.0, f)
        else:
            x0 = centre.copy()
            sc = np.full(3, radius)

            def fun(p):
                return _cone_residuals(rays, o, p, radius, 0.0, f)
        sol = least_squares(fun, x0, loss="soft_l1", f_scale=0.5, x_scale=sc, method="trf")
        if mode == "plane":
            centre = np.array([sol.x[0], sol.x[1], z])
        else:
            centre = sol.x.copy()
        res = fun(sol.x)
    ctr_px = cam.project(centre)
    dist = np.linalg.norm(centre - o)
    r_px = f * np.tan(np.arcsin(min(radius / dist, 1.0)))
    if frac < 0.98:
        raise InputError(f"the chrome ball (centre at pixel ({ctr_px[0]:.0f}, {ctr_px[1]:.0f}), radius "
                         f"{r_px:.0f} px) is cut by the image edge", source, SHOOT_BALL)
    if res is None:
        raise InputError("found no silhouette edges around the chrome ball", source, SHOOT_BALL)
    inl = np.abs(res) < 1.5
    rms = float(np.sqrt(np.mean(res[inl] ** 2))) if inl.any() else float("inf")
    bias = float(np.median(res))  # > 0: the edges lie outside the predicted silhouette
    fit = BallFit(centre, float(radius), rms, ctr_px, float(r_px), bias, n_edges=int(len(res)),
                  inlier_fraction=float(inl.mean()), mode=mode)
    if mode != "free" and abs(bias) > max(MAX_EDGE_BIAS_PX, 0.03 * r_px):
        fit.warnings.append(f"the silhouette is {bias:+.1f} px off the size a {2 * radius * 1000:.0f} mm ball "
                            + ("on the plane z = 0 " if mode == "plane" else "at the known centre ")
                            + "would have: check the ball diameter" + (" and that it rests on the support"
                                                                      if mode == "plane" else ""))
    if fit.inlier_fraction < 0.5:
        fit.warnings.append(f"only {100 * fit.inlier_fraction:.0f}% of the silhouette has a clear edge")
    return fit


def _choose(cands: list[_Candidate], radius: float, plane: bool, source) -> _Candidate:
    """The ball among the candidates (full-resolution pixels), or the InputError that says why there is none."""
    def at(c):
        return f"({c.ctr_px[0]:.0f}, {c.ctr_px[1]:.0f})"

    good = [c for c in cands if c.support >= MIN_SUPPORT]
    if not good:
        cut = [c for c in cands if 0.5 <= c.inside < 0.98 and c.raw >= MIN_SUPPORT + CUT_MARGIN]
        if cut:
            raise InputError(f"the chrome ball (centre near pixel {at(cut[0])}) is cut by the image edge", source,
                             SHOOT_BALL)
        where = "on the plane z = 0 " if plane else ""
        best = f" (best edge support {cands[0].support:.2f} < {MIN_SUPPORT})" if cands else ""
        raise InputError(f"no chrome ball of diameter {2000 * radius:.0f} mm {where}found{best}", source,
                         SHOOT_BALL + "; check the ball diameter and the camera")
    best = good[0]
    if plane:
        twins = [c for c in good[1:] if c.support >= TWIN_RATIO * best.support and _disjoint(c, best)]
    else:  # without the plane, textured backgrounds offer ball-like circles of any size: be stricter
        twins = [c for c in good[1:] if c.support >= TWIN_RATIO_FREE * best.support and _disjoint(c, best)
                 and max(c.r_px, best.r_px) < 1.3 * min(c.r_px, best.r_px)]
    if twins:
        raise InputError(f"two ball-like silhouettes found, at pixels {at(best)} and {at(twins[0])}", source,
                         "keep one chrome ball in view, or give the ball's known centre")
    if best.inside < 0.98:
        raise InputError(f"the chrome ball (centre near pixel {at(best)}) is cut by the image edge", source,
                         SHOOT_BALL)
    return best


# ------------------------------------------------------------------------------------------------- API


def fit_ball(hdr, camera: Camera, radius: float, known_centre=None, rests_on_plane: bool = True,
             approx_px=None, skip_contact: float = CONTACT_SKIP, source: str | Path | None = None,
             valid: np.ndarray | None = None, use_rim: bool = True, contact_arc: str = "auto") -> BallFit:
    """Find and fit a chrome ball of ``radius`` metres in ``hdr`` (H, W, 3) linear radiance (or a
    :class:`~objcam.capture.hdr.MergeResult`) seen by ``camera``.

    known_centre: (3,) world centre, if measured: no search, no fit (edges still measured for ``residual_px``).
    rests_on_plane: the ball lies on z = 0, so its centre is at z = radius (see the module doc).
    approx_px: (u, v, r) rough image centre and apparent radius in pixels (e.g. clicked): skips the detection;
    the refinement starts from it (within ~3 px).
    contact_arc: "auto", "fit" or "skip": the skipped arc refitted when its edges agree with the rest, always, or
    never (see the module doc, step 3). use_rim: the rim model's refinement (step 4) for balls of
    ``RIM_MIN_RADIUS_PX`` or more. valid: (H, W) bool, False where saturated in every frame (default: the
    MergeResult's); the rim model leaves those pixels out.
    skip_contact: with ``rests_on_plane``, silhouette points whose background is the plane within this many
    radii of the contact point are not fitted (contact shadow; 0: fit them, e.g. for a floating ball).
    source: the file named in errors (default: the longest frame of a MergeResult).
    Raises InputError (no ball, two balls, ball cut by the image edge), naming ``source``.
    """
    import cv2

    if hasattr(hdr, "radiance"):
        source = source or (hdr.paths[-1] if hdr.paths else None)
        if valid is None:
            valid = getattr(hdr, "valid", None)
        hdr = hdr.radiance
    hdr = np.asarray(hdr, np.float32)
    if hdr.shape[:2] != (camera.height, camera.width):
        raise InputError(f"image is {hdr.shape[1]}x{hdr.shape[0]} but its camera says "
                         f"{camera.width}x{camera.height}", source, "give the camera of this image")
    if not radius > 0:
        raise ValueError("radius must be > 0")
    logc = log_rgb(hdr)
    if known_centre is not None:
        known = np.asarray(known_centre, np.float64)
        fit = _refine(logc, camera, radius, known, "known", source, windows=(2.0,))
        # check it against the photo: the centre the silhouette asks for at the known height
        try:
            check = _refine(logc, camera, radius, known, "plane", source, WINDOWS, 0.0)
            check = _finish(hdr, valid, logc, camera, radius, check.centre_world, "plane", source, 0.0, use_rim)
        except InputError as e:  # the known centre stays in use; say why it could not be checked
            fit.warnings.append(f"the known centre could not be checked against the photo ({e.args[0]})")
            return fit
        fit.fitted_offset_mm = float(1e3 * np.linalg.norm(check.centre_world - known))
        fit.rim = check.rim
        if fit.fitted_offset_mm > KNOWN_TOLERANCE_MM:
            fit.warnings.append(f"the photo puts the ball {fit.fitted_offset_mm:.1f} mm from the known centre "
                                f"{tuple(round(float(x), 4) for x in known)} (at its height): check [[probes]] "
                                "centre, the diameter and the camera")
        return fit
    mode = "plane" if rests_on_plane else "free"
    if approx_px is not None:
        params = np.asarray(approx_px, np.float64)[None, :3 if not rests_on_plane else 2]
        centre = _centres_of(camera, params if rests_on_plane else params, radius, rests_on_plane)[0]
        if not np.all(np.isfinite(centre)):
            raise InputError(f"approx_px {tuple(approx_px)} does not meet the plane z = {radius} in front of the "
                             "camera", source, "check the pixel position and the camera")
        fit = _refine(logc, camera, radius, centre, mode, source, (4.0,) + WINDOWS, skip_contact)  # no pyramid
        return _finish(hdr, valid, logc, camera, radius, fit.centre_world, mode, source, skip_contact, use_rim,
                   contact_arc)
    # detection on a shrunk copy
    s = max(1.0, min(camera.width, camera.height) / DETECT_SIZE)
    small, cam_s = _shrink(hdr[..., :3], camera, s)
    s = camera.width / cam_s.width
    lsmall = log_luminance(small)
    ls = _smooth(lsmall, 1.0)
    gx = cv2.Sobel(ls, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(ls, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    tau = max(float(np.percentile(np.hypot(gx, gy), 90)), 1e-6)
    if rests_on_plane:
        cands = _candidates_plane(cam_s, gx, gy, tau, radius, MIN_RADIUS_PX / s)
    else:
        cands = _candidates_free(cam_s, ls, gx, gy, tau, radius, MIN_RADIUS_PX / s)
    for c in cands:  # back to full-resolution pixels
        c.ctr_px = (c.ctr_px + 0.5) * s - 0.5
        c.r_px *= s
    best = _choose(cands, radius, rests_on_plane, source)
    centre = best.centre
    level = 2.0 ** int(np.floor(np.log2(s)))
    while level > 1.0:  # coarse to fine: each level starts within ~1 of its pixels
        img_l, cam_l = _shrink(hdr[..., :3], camera, level)
        centre = _refine(log_rgb(img_l), cam_l, radius, centre, mode, source, WINDOWS[:3], skip_contact).centre_world
        level /= 2.0
    fit = _refine(logc, camera, radius, centre, mode, source, WINDOWS, skip_contact)
    fit = _finish(hdr, valid, logc, camera, radius, fit.centre_world, mode, source, skip_contact, use_rim,
                   contact_arc)
    fit.support = best.support
    return fit


def _finish(hdr, valid, logc, cam: Camera, radius: float, centre: np.ndarray, mode: str, source,
            skip_contact: float, use_rim: bool, contact_arc: str = "auto") -> BallFit:
    """The last steps after the edge fit at full resolution (``centre``): in plane mode, the contact arc is
    fitted too when its edges agree with the rest (a ball with no contact shadow: floating, or on a support
    that does not darken next to it); then the rim model (objcam.probe.rim) from there, kept when it moves the
    silhouette by at most ``RIM_MAX_SHIFT_PX``. Returns the fit with its edge statistics at the final centre."""
    skip = skip_contact if mode == "plane" else 0.0
    arc = "n/a"
    if skip > 0:
        arc = "skipped"
        if contact_arc == "fit" or (contact_arc == "auto" and _contact_arc_agrees(logc, cam, centre, radius, skip)):
            arc = "fitted"
            skip = 0.0
            centre = _refine(logc, cam, radius, centre, mode, source, WINDOWS[-2:], 0.0).centre_world
    edge_centre = centre.copy()
    rim = None
    r_px = _focal(cam) * np.tan(np.arcsin(min(radius / np.linalg.norm(centre - cam.centre), 1.0)))
    if use_rim and r_px >= RIM_MIN_RADIUS_PX:
        rf = refine_rim(hdr, valid, cam, radius, centre, plane=mode == "plane", skip_contact=skip)
        if rf is not None:
            shift = _silhouette_shift_px(cam, radius, centre, rf.centre)
            used = bool(shift <= RIM_MAX_SHIFT_PX)
            rim = dict(rf.to_dict(), used=used, shift_px=shift)
            if used:
                centre = rf.centre
    fit = _refine(logc, cam, radius, centre, "known", source, windows=(1.5,), skip_contact=skip)
    fit.mode = mode
    fit.contact_arc = arc
    fit.edge_centre_world = edge_centre
    fit.rim = rim
    return fit


def _contact_arc_agrees(logc, cam: Camera, centre: np.ndarray, radius: float, skip: float) -> bool:
    """Whether the silhouette's contact arc (see :func:`_contact_arc`) has clean edges that agree with the rest
    of the silhouette at the fit made without it: edges found on >= ``ARC_FOUND`` of its points, their median
    residual within ``ARC_BIAS_PX`` of the rest's, and >= ``ARC_INLIERS`` of them within ``ARC_SPREAD_PX`` of the
    rest's median. Measured fractions: 0.92-1.0 for floating balls; 0.4-0.9 resting on a rendered diffuse plane
    (refused at 300 px, accepted at 1000 px, where fitting the arc still helped, module doc step 3); an arc with
    no edges left (a deep shadow reflected in the ball) is refused."""
    dist = np.linalg.norm(centre - cam.centre)
    alpha = np.arcsin(min(radius / dist, 1.0))
    k = int(np.clip(2 * np.pi * _focal(cam) * np.tan(alpha), 64, 4096))
    rays = silhouette_rays(centre, radius, cam.centre, 2 * np.pi * np.arange(k) / k)
    n_arc = int(_contact_arc(cam, rays, centre, radius, skip).sum())
    if n_arc < 8:
        return False
    f = _focal(cam)
    arc, _, _ = _edge_points(logc, cam, centre, radius, 0.0, WINDOWS[-1], skip, contact_only=True)
    rest, _, _ = _edge_points(logc, cam, centre, radius, 0.0, WINDOWS[-1], skip)
    if len(arc) < ARC_FOUND * n_arc or len(rest) < 16:
        return False
    r_arc = _cone_residuals(_pixel_rays(cam, arc), cam.centre, centre, radius, 0.0, f)
    m_rest = float(np.median(_cone_residuals(_pixel_rays(cam, rest), cam.centre, centre, radius, 0.0, f)))
    return bool(abs(np.median(r_arc) - m_rest) <= ARC_BIAS_PX
                and np.mean(np.abs(r_arc - m_rest) < ARC_SPREAD_PX) >= ARC_INLIERS)


def _silhouette_shift_px(cam: Camera, radius: float, a: np.ndarray, b: np.ndarray) -> float:
    """Largest image distance (pixels) between the silhouettes of balls at ``a`` and ``b``."""
    pa = silhouette_px(cam, np.asarray(a)[None], radius, 64)[0]
    pb = silhouette_px(cam, np.asarray(b)[None], radius, 64)[0]
    return float(np.max(np.linalg.norm(pa - pb, axis=-1)))
