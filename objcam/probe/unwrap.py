"""Unwrap a fitted chrome ball into an environment map (objcam's lat-long convention, objcam/envmap.py).

For every texel centre direction ``d`` of a fine grid (default 512 x 1024) the point of the sphere that mirrors
``d`` into the camera is found exactly (perspective: :func:`objcam.probe.optics.reflection_points`), projected
into the image and sampled (``cv2.remap``, bicubic by default); the radiance is the sample divided by the ball's
reflectance at that incidence angle (:class:`objcam.probe.optics.Reflectance`). The fine map is then area-averaged
(solid-angle exact, :func:`objcam.envmap.area_downsample` weights) to the solve resolution: point sampling a
coarse grid instead loses or gains the energy of small bright sources. The fine grid should be at least as fine
as one image pixel at the ball's centre (2 / r_px rad, r_px the apparent radius): 512 rows (0.35 deg) up to
r_px ~ 330, 1024 beyond (:func:`objcam.probe.recover.recover_probe` picks it). Measured: the area-averaged
energy of a 1-pixel sun is stable to 0.1 % from 512 to 1536 rows with bilinear sampling; nearest-pixel sampling
blurs less (per-texel RMSE without the sun 0.034 instead of 0.042 at 256 px) but its sun energy wobbles +-2 %
with the grid. Bicubic (OpenCV's Keys kernel) is an interpolating kernel whose blur is far below bilinear's (the
tent adds its own pixel of blur to the pixels' box), so a bright texel leaks less into its neighbours: measured on
clean 1400 px renders (ball 1000 px, 1024 rows, 32 x 64): forest 0.033 instead of 0.044, courtyard 0.024 instead
of 0.030 (Lanczos-4: the same as bicubic). Its ringing can leave small negative values in the fine map right
beside a very bright source; they cancel in any area average (the coarse map is clipped at 0 only to remove
round-off).

Masks (bit flags in :attr:`ProbeEnvmap.flags`; a texel is valid when it has none):

- ``BLIND`` (1): incidence angle above ``max_incidence_deg`` (default 80): the directions within
  ``2 * (90 - 80) = 20`` deg of straight behind the ball, seen squeezed into its rim (unreliable: a pixel there
  covers tens of degrees, and any error in the fitted silhouette moves them a lot).
- ``CAMERA`` (2): within ``camera_cone_deg`` (default 10) of the direction from the ball to the camera: the
  camera and photographer reflected in the ball (10 deg is a 12 cm wide camera at 35 cm, tripod head
  included).
- ``SATURATED`` (4): the interpolation footprint touches a pixel saturated in every bracket frame (``valid = False`` in
  the merge). Their radiance is kept but is a LOWER BOUND; :attr:`ProbeEnvmap.lower_bound` says whether any
  texel is affected.
- ``OUTSIDE`` (8): the reflection point projects outside the image (or no reflection point converged).

Low resolution (:meth:`ProbeEnvmap.downsample`): each coarse texel averages its fine texels weighted by solid
angle over those that are valid or saturated (observed). It is valid when its valid fine texels cover at least
``min_valid_fraction`` (default 0.5) of its solid angle AND none of its observed fine texels is saturated;
a coarse texel containing a saturated fine texel is flagged saturated (value = lower bound). Coarse texels with
no observed fine texel are 0.

Units: the unwrapped radiance has the units of the HDR image (divide by the merge's reference time, or align
exposures, to compare with images in other units).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from objcam.camera import Camera
from objcam.envmap import EnvGrid
from objcam.probe.optics import Reflectance, normalise, reflection_points

BLIND, CAMERA, SATURATED, OUTSIDE = 1, 2, 4, 8
FLAG_NAMES = {BLIND: "blind spot (grazing)", CAMERA: "camera reflection", SATURATED: "saturated (lower bound)",
              OUTSIDE: "outside the image"}


@dataclass
class ProbeEnvmap:
    """An unwrapped chrome-ball probe on a fine lat-long grid."""

    envmap: np.ndarray  # (H, 2H, 3) float32 radiance; 0 where not observed (BLIND, CAMERA, OUTSIDE)
    flags: np.ndarray  # (H, 2H) uint8 mask bits (see the module doc); 0 = valid
    cos_incidence: np.ndarray  # (H, 2H) float32 incidence cosine on the ball
    projection: str  # "perspective" or "orthographic"
    footprint_deg: np.ndarray | None = None  # (H, 2H) float32 largest angle one image pixel spans there (deg)

    @property
    def valid(self) -> np.ndarray:
        return self.flags == 0

    @property
    def saturated(self) -> np.ndarray:
        return (self.flags & SATURATED) != 0

    @property
    def observed(self) -> np.ndarray:
        """Texels with a radiance sample (valid or saturated)."""
        return (self.flags & np.uint8(0xFF ^ SATURATED)) == 0

    @property
    def lower_bound(self) -> bool:
        """True when some texel's radiance is a lower bound (saturated in every frame)."""
        return bool(self.saturated.any())

    def downsample(self, height: int, min_valid_fraction: float = 0.5, max_footprint: float | None = None):
        """(envmap (h, 2h, 3), valid (h, 2h) bool, saturated (h, 2h) bool) at ``height`` rows (see the module
        doc); the fine height must be a multiple of ``height``. ``max_footprint``: fine texels where one image
        pixel spans more than this fraction of a coarse texel's height (180 / height deg) count as invalid
        (resolution-limited: their pixels blur energy across coarse texels); None: no such limit."""
        src_h = self.envmap.shape[0]
        if src_h % height:
            raise ValueError(f"probe height {src_h} is not a multiple of {height}")
        f = src_h // height
        w = EnvGrid(src_h).solid_angles()
        obs = self.observed
        wo = w * obs
        good = self.valid
        if max_footprint is not None and self.footprint_deg is not None:
            good = good & (self.footprint_deg <= max_footprint * 180.0 / height)
        wv = w * good

        def pool(a):
            return a.reshape(height, f, 2 * height, f, *a.shape[2:]).sum(axis=(1, 3))

        num = pool(self.envmap.astype(np.float64) * wo[..., None])
        den = pool(wo)
        total = pool(w)
        env = np.where(den[..., None] > 0, num / np.maximum(den, 1e-300)[..., None], 0.0)
        env = np.maximum(env, 0.0)  # bicubic ringing cancels in the average; this only removes round-off
        sat = pool(self.saturated.astype(np.float64)) > 0
        valid = (pool(wv) >= min_valid_fraction * total) & ~sat
        return env.astype(np.float32), valid, sat

    def summary(self) -> dict:
        n = self.flags.size
        w = EnvGrid(self.flags.shape[0]).solid_angles()
        out = {"valid_fraction_solid_angle": float((w * self.valid).sum() / w.sum()),
               "valid_texels": int(self.valid.sum()), "texels": int(n), "lower_bound": self.lower_bound,
               "projection": self.projection}
        for bit, name in FLAG_NAMES.items():
            out[f"flag_{bit}_{name.split(' ')[0]}"] = float((w * ((self.flags & bit) != 0)).sum() / w.sum())
        return out


INTERPOLATIONS = ("cubic", "linear")


def _remap(img: np.ndarray, u: np.ndarray, v: np.ndarray, interpolation: str = "linear") -> np.ndarray:
    """Samples (..., C) of ``img`` (H, W, C) at pixel positions (OpenCV centres) via cv2.remap, bicubic
    (``"cubic"``) or bilinear (``"linear"``)."""
    import cv2

    shape = u.shape
    n = u.size
    cols = 1024
    rows = -(-n // cols)
    pad = rows * cols - n
    mu = np.pad(u.ravel().astype(np.float32), (0, pad), constant_values=-10).reshape(rows, cols)
    mv = np.pad(v.ravel().astype(np.float32), (0, pad), constant_values=-10).reshape(rows, cols)
    mode = cv2.INTER_CUBIC if interpolation == "cubic" else cv2.INTER_LINEAR
    out = cv2.remap(np.ascontiguousarray(img, np.float32), mu, mv, mode, borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(rows * cols, -1)[:n]
    return out.reshape(*shape, -1)


def unwrap(hdr, camera: Camera, centre, radius: float, *, height: int = 512,
           reflectance: Reflectance | None = None, max_incidence_deg: float = 80.0,
           camera_cone_deg: float = 10.0, valid: np.ndarray | None = None,
           projection: str = "perspective", interpolation: str = "cubic") -> ProbeEnvmap:
    """Unwrap the ball (world ``centre`` (3,), ``radius`` metres) seen in ``hdr`` (H, W, 3) linear radiance, or a
    :class:`~objcam.capture.hdr.MergeResult` (its ``valid`` mask is used), through ``camera``.

    height: rows of the fine lat-long grid (width 2 * height). reflectance: the ball's (default
    ``Reflectance()``: 0.65 at normal incidence, chromium's Fresnel shape towards grazing). valid: (H, W) bool,
    False where the pixel is saturated in every frame (overrides the merge's). projection: ``"perspective"``
    (exact) or ``"orthographic"`` (the textbook shortcut that treats the camera as infinitely far; for
    comparison only). interpolation: ``"cubic"`` (default, least blur) or ``"linear"`` (see the module doc).
    """
    if hasattr(hdr, "radiance"):
        if valid is None:
            valid = hdr.valid
        hdr = hdr.radiance
    if projection not in ("perspective", "orthographic"):
        raise ValueError("projection must be 'perspective' or 'orthographic'")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}")
    refl = reflectance or Reflectance()
    img = np.asarray(hdr, np.float32)[..., :3]
    hh, ww = img.shape[:2]
    c = np.asarray(centre, np.float64)
    o = camera.centre
    grid = EnvGrid(height)
    d = grid.directions()
    rp = reflection_points(d, c, radius, o, orthographic=projection == "orthographic")
    if projection == "orthographic":
        # the shortcut: the ball's image is an orthographic view scaled to the apparent radius, centred on the
        # projection of the centre, in the camera's image axes
        r_px = np.sqrt(camera.fx * camera.fy) * np.tan(np.arcsin(min(radius / np.linalg.norm(c - o), 1.0)))
        rot = camera.matrix[:3, :3]
        ctr = camera.project(c)
        local = (rp.normal @ rot)  # camera-frame normal
        uv = np.stack([ctr[0] + r_px * local[..., 0], ctr[1] + r_px * local[..., 1]], -1)
    else:
        uv = camera.project(rp.point)
    u, v = uv[..., 0], uv[..., 1]
    flags = np.zeros(grid.shape, np.uint8)
    flags[rp.cos_i < np.cos(np.radians(max_incidence_deg))] |= BLIND
    to_cam = normalise(o - c)
    flags[d @ to_cam > np.cos(np.radians(camera_cone_deg))] |= CAMERA
    inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u <= ww - 1) & (v >= 0) & (v <= hh - 1) & rp.converged
    flags[~inside] |= OUTSIDE
    uu = np.where(inside, u, -10.0)
    vv = np.where(inside, v, -10.0)
    rad = _remap(img, uu, vv, interpolation)
    if valid is not None:
        bad = (~np.asarray(valid, bool)).astype(np.float32)[..., None]
        # any saturated pixel in the interpolation footprint: the interpolated weight of bad pixels is nonzero
        # (bicubic weights can be negative, hence the absolute value)
        touch = np.abs(_remap(bad, uu, vv, interpolation)[..., 0]) > 1e-6
        flags[touch & inside] |= SATURATED
    rad = rad / refl(rp.cos_i).astype(np.float32)
    observed = (flags & np.uint8(0xFF ^ SATURATED)) == 0
    env = np.where(observed[..., None], rad, 0.0).astype(np.float32)
    return ProbeEnvmap(env, flags, rp.cos_i.astype(np.float32), projection, pixel_footprint_deg(uv))


def pixel_footprint_deg(uv: np.ndarray) -> np.ndarray:
    """(H, 2H) largest angle (degrees) that one image pixel spans in direction space, from the image positions
    ``uv`` (H, 2H, 2) of a lat-long grid's texel centres: 1 / (smallest singular value of d(u, v) / d(direction))
    by central differences (columns wrap; NaN where a neighbour is not finite)."""
    h, w = uv.shape[:2]
    dt = np.pi / h
    theta = np.pi * (np.arange(h) + 0.5) / h
    dp = (2 * np.pi / w) * np.sin(theta)[:, None, None]
    up = np.concatenate([uv[:1], uv[:-1]], axis=0)
    dn = np.concatenate([uv[1:], uv[-1:]], axis=0)
    rows = np.arange(h)
    span = np.where((rows == 0) | (rows == h - 1), 1.0, 2.0)[:, None, None]
    j_t = (dn - up) / (span * dt)
    j_p = (np.roll(uv, -1, axis=1) - np.roll(uv, 1, axis=1)) / (2 * dp)
    a, c = j_t[..., 0], j_t[..., 1]
    b, d = j_p[..., 0], j_p[..., 1]
    # singular values of [[a, b], [c, d]]
    s1 = a * a + b * b + c * c + d * d
    det = np.abs(a * d - b * c)
    s_min = np.sqrt(np.maximum(0.5 * (s1 - np.sqrt(np.maximum(s1 * s1 - 4 * det * det, 0))), 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.degrees(1.0 / s_min).astype(np.float32)
