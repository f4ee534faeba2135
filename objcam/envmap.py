"""The environment-map grid: objcam's one definition of the lat-long convention.

World frame: metres, z up. An envmap is an equirectangular image of shape (H, W=2H, C) holding linear RGB
radiance. Row 0 is the zenith (+z), the last row the nadir. Column c covers azimuth
phi = 2*pi*(c+0.5)/W measured from +x towards +y. The texel centre direction is
(cos phi sin theta, sin phi sin theta, cos theta) with theta = pi*(r+0.5)/H.

Every module that maps between directions and texels goes through this file; the conversion to Mitsuba's
y-up envmap lives in :func:`mitsuba_envmap_to_world` and nowhere else.

Files use a different, standard convention: every lat-long image objcam reads or writes (EXR, HDR or PNG) is the
equirectangular panorama of z-up worlds (Blender, Poly Haven HDRIs): column u in [0, 1) looks along
u = 0.5 - atan2(y, x) / (2 pi) (mod 1), so +x is the centre column, +y a quarter of the width from the left, and
azimuth turns clockwise seen from above as u grows. :func:`to_file` and :func:`from_file` convert between the two
(and :func:`read_latlong`, :func:`write_latlong`, :func:`write_latlong_png` wrap the I/O); nothing else does.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class EnvGrid:
    """A lat-long grid of ``height`` rows and ``2 * height`` columns."""

    height: int

    @property
    def width(self) -> int:
        return 2 * self.height

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def n_texels(self) -> int:
        return self.height * self.width

    def theta_edges(self) -> np.ndarray:
        """(H+1,) polar angle of the row boundaries, radians, 0 at the zenith."""
        return np.linspace(0.0, np.pi, self.height + 1)

    def phi_edges(self) -> np.ndarray:
        """(W+1,) azimuth of the column boundaries, radians, from +x towards +y."""
        return np.linspace(0.0, 2.0 * np.pi, self.width + 1)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(theta, phi) of the texel centres, each (H, W) radians."""
        theta = np.pi * (np.arange(self.height) + 0.5) / self.height
        phi = 2.0 * np.pi * (np.arange(self.width) + 0.5) / self.width
        return np.meshgrid(theta, phi, indexing="ij")

    def directions(self) -> np.ndarray:
        """(H, W, 3) unit world directions of the texel centres."""
        theta, phi = self.centres()
        return spherical_to_direction(theta, phi)

    def solid_angles(self) -> np.ndarray:
        """(H, W) exact solid angle of every texel in steradians; sums to 4*pi."""
        t = self.theta_edges()
        band = (np.cos(t[:-1]) - np.cos(t[1:])) * (2.0 * np.pi / self.width)
        return np.repeat(band[:, None], self.width, axis=1)

    def texel_of(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices of the texels containing unit directions ``d`` (..., 3)."""
        theta, phi = direction_to_spherical(d)
        r = np.clip((theta / np.pi * self.height).astype(np.int64), 0, self.height - 1)
        c = np.clip((phi / (2 * np.pi) * self.width).astype(np.int64), 0, self.width - 1)
        return r, c

    def sample_in_texels(self, u: np.ndarray, v: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Directions uniformly distributed in solid angle inside texels.

        ``u, v`` in [0, 1) (any broadcastable shape) pick the point; ``rows, cols`` the texel. Uniform in
        solid angle means uniform in cos(theta) across the row band and uniform in phi.
        """
        t = self.theta_edges()
        cos_top, cos_bot = np.cos(t[rows]), np.cos(t[rows + 1])
        cos_theta = cos_top + (cos_bot - cos_top) * u
        phi = 2.0 * np.pi * (cols + v) / self.width
        sin_theta = np.sqrt(np.clip(1.0 - cos_theta**2, 0.0, 1.0))
        return np.stack([np.cos(phi) * sin_theta, np.sin(phi) * sin_theta, cos_theta], axis=-1)


def spherical_to_direction(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3) for polar angle ``theta`` from +z and azimuth ``phi`` from +x towards +y."""
    st = np.sin(theta)
    return np.stack([np.cos(phi) * st, np.sin(phi) * st, np.cos(theta)], axis=-1)


def direction_to_spherical(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of unit vectors ``d`` (..., 3); phi in [0, 2*pi)."""
    theta = np.arccos(np.clip(d[..., 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[..., 1], d[..., 0]), 2.0 * np.pi)
    return theta, phi


def area_downsample(env: np.ndarray, height: int) -> np.ndarray:
    """Area-average a lat-long map (H, 2H[, C]) to ``height`` rows, weighting by solid angle.

    The input height must be a multiple of ``height``. Returns radiance (mean over the solid angle of each
    output texel), so the integral of radiance times solid angle is preserved exactly.
    """
    src_h = env.shape[0]
    if src_h % height:
        raise ValueError(f"envmap height {src_h} is not a multiple of {height}")
    f = src_h // height
    w = EnvGrid(src_h).solid_angles()
    squeeze = env.ndim == 2
    e = env[..., None] if squeeze else env
    weighted = e * w[..., None]
    out_w = 2 * height
    num = weighted.reshape(height, f, out_w, f, -1).sum(axis=(1, 3))
    den = w.reshape(height, f, out_w, f).sum(axis=(1, 3))[..., None]
    out = num / den
    return out[..., 0] if squeeze else out


def resample_to_height(env: np.ndarray, height: int) -> np.ndarray:
    """Bring a lat-long map to ``height`` rows: area-average when shrinking by an integer factor, otherwise
    supersample by nearest-texel repetition to a common multiple first (exact for box texels)."""
    src_h = env.shape[0]
    if src_h == height:
        return env.copy()
    if src_h % height == 0:
        return area_downsample(env, height)
    lcm = np.lcm(src_h, height)
    up = lcm // src_h
    big = np.repeat(np.repeat(env, up, axis=0), up, axis=1)
    return area_downsample(big, height)


def rotate_z(env: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate a lat-long map about +z by ``degrees`` (a source at azimuth phi moves to phi + degrees).

    Whole-texel shifts are exact; fractional parts are linearly interpolated along the row.
    """
    w = env.shape[1]
    shift = degrees / 360.0 * w
    k = int(np.floor(shift))
    frac = shift - k
    a = np.roll(env, k, axis=1)
    if frac == 0.0:
        return a
    b = np.roll(env, k + 1, axis=1)
    return (1.0 - frac) * a + frac * b


def to_mitsuba_bitmap(env: np.ndarray) -> np.ndarray:
    """The array to hand Mitsuba's ``envmap`` emitter (with :func:`mitsuba_envmap_to_world`) for an envmap in
    objcam's convention: the columns reversed.

    Mitsuba 3 looks a local direction d up at u = atan2(d.x, -d.z) / (2 pi) (mod 1), v = acos(d.y) / pi, so its
    azimuth turns clockwise about its up axis seen from above, ours anticlockwise about +z. Reversing the columns
    lets a proper rotation (no mirror in ``to_world``) do the rest.
    """
    return np.ascontiguousarray(env[:, ::-1])


def mitsuba_envmap_to_world() -> np.ndarray:
    """4x4 ``to_world`` for Mitsuba's ``envmap`` emitter holding :func:`to_mitsuba_bitmap` of an envmap.

    With reversed columns, our column c sits at Mitsuba u' = 1 - (c + 0.5)/W, where atan2(d.x, -d.z) = -phi,
    i.e. local (x, y, z) = (-sin phi sin theta, cos theta, -cos phi sin theta). Hence local x -> world -y,
    local y -> world +z, local z -> world -x: a rotation (determinant +1). tests/test_conventions.py renders single
    texels through Mitsuba and checks they land where this module says.
    """
    m = np.zeros((4, 4))
    m[:3, 0] = [0.0, -1.0, 0.0]  # local x -> world -y
    m[:3, 1] = [0.0, 0.0, 1.0]  # local y (Mitsuba's up) -> world +z
    m[:3, 2] = [-1.0, 0.0, 0.0]  # local z -> world -x
    m[3, 3] = 1.0
    return m


def to_file(env: np.ndarray) -> np.ndarray:
    """objcam's grid (H, W[, C]) -> the standard z-up equirectangular layout written to files.

    objcam's column c (azimuth phi = 2 pi (c + 0.5) / W from +x towards +y) lands at file u = 0.5 - phi / (2 pi),
    i.e. file column (W/2 - 1 - c) mod W: the columns reversed, then rolled by half the width. Exact (a column
    permutation) and its own inverse.
    """
    return np.ascontiguousarray(np.roll(np.asarray(env)[:, ::-1], env.shape[1] // 2, axis=1))


def from_file(env: np.ndarray) -> np.ndarray:
    """The standard z-up equirectangular layout of a file (H, W[, C]) -> objcam's grid (the inverse of
    :func:`to_file`, which is the same permutation)."""
    return to_file(env)


def read_latlong(path: str | Path) -> np.ndarray:
    """A lat-long EXR (standard convention) as objcam's grid (H, W, C) float32."""
    from objcam.image_io import read_exr

    return from_file(read_exr(path))


def write_latlong(path: str | Path, env: np.ndarray, half: bool = False) -> None:
    """Write objcam's grid ``env`` (H, W[, C]) as an EXR in the standard convention (atomically)."""
    from objcam.image_io import write_exr

    write_exr(path, to_file(env), half=half)


def write_latlong_png(path: str | Path, display: np.ndarray) -> None:
    """Write a display image (H, W[, C], values in [0, 1]) of objcam's grid as a PNG in the standard convention."""
    from objcam.image_io import write_png

    write_png(path, to_file(display))


def read_latlong_mask(path: str | Path) -> np.ndarray:
    """A lat-long mask PNG (standard convention, nonzero > 127 = set) as objcam's grid (H, W) bool."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(path)
    img = img if img.ndim == 2 else img[..., 0]
    return from_file(img > 127)


def standard_mitsuba_to_world() -> np.ndarray:
    """4x4 ``to_world`` for Mitsuba 3's ``envmap`` emitter holding a lat-long FILE (standard convention) as is.

    Mitsuba looks local direction l up at u = atan2(l.x, -l.z) / (2 pi), v = acos(l.y) / pi. The file's
    u = 0.5 - atan2(y, x) / (2 pi) needs l = (y, z, x) of the world direction (x, y, z): local x -> world +y,
    local y -> world +z, local z -> world +x (a cyclic permutation, determinant +1).
    """
    m = np.zeros((4, 4))
    m[:3, 0] = [0.0, 1.0, 0.0]
    m[:3, 1] = [0.0, 0.0, 1.0]
    m[:3, 2] = [1.0, 0.0, 0.0]
    m[3, 3] = 1.0
    return m
