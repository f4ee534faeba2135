"""Procedural lighting for the hard-case suite: lat-long envmaps (H, 2H, 3) in the convention of data_layout.md
(row 0 the zenith, azimuth from +x towards +y, texel centre (cos phi sin theta, sin phi sin theta, cos theta)),
written here from that text alone, not from objcam's envmap module. Files (the bundled HDRIs read, truth/ written)
are in data_layout.md's standard file convention: :func:`file_columns` converts, from the formula there.

Every family is a function of an azimuth rotation (degrees, anticlockwise about +z seen from above) so each
rotation is drawn exactly, not resampled; the bundled HDRIs are rotated by whole columns of the 256 x 512 grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

HEIGHT = 256  # truth grid: 0.7 deg texels resolve a 2 deg lamp; 8 x the solve's 32 rows (exact area average)
HDRIS = ("forest", "courtyard", "city", "sunrise", "sunset")
ASSETS = Path(__file__).resolve().parents[2] / "objcam" / "assets" / "envmaps"
#: the held-out design's HDRIs: the other three of Blender's CC0 worlds, which objcam does not bundle
#: (bench/hard/envmaps/, made by scripts/make_assets.py)
HELD_OUT_HDRIS = ("interior", "night", "studio")
HELD_OUT_ASSETS = Path(__file__).resolve().parent / "envmaps"


@dataclass(frozen=True)
class Lighting:
    """One lighting condition: ``family`` (lamp, room, window, sun, overcast, hdri), a ``name`` and its knobs."""

    family: str
    name: str
    elevation_deg: float = 0.0  # the lamp's or the sun's
    hdri: str = ""
    window: tuple[float, float, float, float] = (5.0, 35.0, 40.0, 200.0)  # elevations, width, azimuth (degrees)


def lightings() -> list[Lighting]:
    """The suite's 16 lighting conditions (issue 22): one 2-degree lamp at six elevations on a dim sky, dark rooms
    with 2 and 5 lamps, a bright window, a low and a high sun with sky, and the bundled HDRIs."""
    out = [Lighting("lamp", f"lamp{e:g}", float(e)) for e in (1, 3, 10, 30, 60, 85)]
    out += [Lighting("room", "room2"), Lighting("room", "room5"), Lighting("window", "window"),
            Lighting("sun", "sun8", 8.0), Lighting("sun", "sun55", 55.0)]
    out += [Lighting("hdri", h, hdri=h) for h in HDRIS]
    return out


def held_out_lightings() -> list[Lighting]:
    """The held-out design's 14 lighting conditions (bench/hard/design.py): the suite's families with knobs it
    never had (lamps at 2, 6, 20, 45 and 75 degrees, rooms of 3 and 4 lamps, a tall narrow window, suns at 20 and
    40 degrees), an overcast sky (no source at all) and the three HDRIs objcam does not bundle."""
    out = [Lighting("lamp", f"lamp{e:g}", float(e)) for e in (2, 6, 20, 45, 75)]
    out += [Lighting("room", "room3"), Lighting("room", "room4"),
            Lighting("window", "window2", window=(10.0, 60.0, 24.0, 80.0)),
            Lighting("sun", "sun20", 20.0), Lighting("sun", "sun40", 40.0), Lighting("overcast", "overcast")]
    out += [Lighting("hdri", h, hdri=h) for h in HELD_OUT_HDRIS]
    return out


def _grid(h: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) texel centres, each (h, 2h)."""
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2 * np.pi * (np.arange(2 * h) + 0.5) / (2 * h)
    return np.meshgrid(theta, phi, indexing="ij")


def _direction(elev_deg: float, az_deg: float) -> np.ndarray:
    t, p = np.radians(90.0 - elev_deg), np.radians(az_deg)
    return np.array([np.cos(p) * np.sin(t), np.sin(p) * np.sin(t), np.cos(t)])


def add_disc(env: np.ndarray, elev_deg: float, az_deg: float, radius_deg: float, rgb) -> None:
    """Add a disc source of angular ``radius_deg`` and radiance ``rgb`` to ``env`` (H, 2H, 3) in place, each texel
    weighted by the fraction of it the disc covers (8 x 8 sub-samples per texel near the disc)."""
    h = env.shape[0]
    w = 2 * h
    d0 = _direction(elev_deg, az_deg)
    cos_r = np.cos(np.radians(radius_deg))
    s = 8
    # rows near the disc only (its polar extent plus one texel)
    t0 = np.radians(90.0 - elev_deg)
    r0 = max(int((t0 - np.radians(radius_deg)) / np.pi * h) - 1, 0)
    r1 = min(int((t0 + np.radians(radius_deg)) / np.pi * h) + 2, h)
    sub = (np.arange(s) + 0.5) / s
    theta = np.pi * (np.arange(r0, r1)[:, None] + sub[None, :]).ravel() / h          # (R s,)
    phi = 2 * np.pi * (np.arange(w)[:, None] + sub[None, :]).ravel() / w            # (W s,)
    st = np.sin(theta)[:, None]
    dots = (np.cos(phi)[None] * st * d0[0] + np.sin(phi)[None] * st * d0[1] + np.cos(theta)[:, None] * d0[2])
    cover = (dots >= cos_r).reshape(r1 - r0, s, w, s).mean(axis=(1, 3))             # (R, W)
    env[r0:r1] += cover[..., None] * np.asarray(rgb, dtype=np.float64)


def _sky(h: int, zenith, horizon, ground) -> np.ndarray:
    """A smooth sky: ``zenith`` to ``horizon`` radiance above, a constant ``ground`` below. (h, 2h, 3)."""
    theta, _ = _grid(h)
    up = np.clip(np.cos(theta), 0, 1)[..., None]
    sky = np.asarray(horizon) + (np.asarray(zenith) - np.asarray(horizon)) * np.sqrt(up)
    return np.where(theta[..., None] < np.pi / 2, sky, np.asarray(ground, dtype=np.float64))


def file_columns(env: np.ndarray) -> np.ndarray:
    """Between the grid above and a standard lat-long file (data_layout.md: file u = 0.5 - atan2(y, x) / (2 pi),
    so grid column c is file column (W/2 - 1 - c) mod W); the permutation is its own inverse."""
    return np.ascontiguousarray(np.roll(env[:, ::-1], env.shape[1] // 2, axis=1))


def _hdri(name: str, rotation_deg: float, h: int) -> tuple[np.ndarray, float]:
    from objcam.image_io import read_exr

    folder = HELD_OUT_ASSETS if name in HELD_OUT_HDRIS else ASSETS
    env = file_columns(read_exr(folder / f"{name}.exr")[..., :3].astype(np.float64))
    f = h // env.shape[0]
    env = np.repeat(np.repeat(env, f, axis=0), f, axis=1)  # box texels: exact
    k = int(round(rotation_deg / 360.0 * env.shape[1]))
    return np.roll(env, k, axis=1), 360.0 * k / env.shape[1]  # a source at column c moves to c + k


def make_envmap(light: Lighting, rotation_deg: float, h: int = HEIGHT) -> tuple[np.ndarray, float]:
    """(envmap (h, 2h, 3) float32 radiance, the rotation actually applied in degrees) for ``light``.

    Radiance levels (ratios are what matter; the targets are in the envmap's units):
    - lamp: a 2-degree disc of radiance 500 (1e4 x the sky) at its elevation, azimuth 30 + rotation, on a dim sky
      (0.05 at the zenith, 0.03 at the horizon, ground 0.01);
    - room2 / room5: a dark room (walls 0.01, floor 0.005) with 2 or 5 lamps of radius 3 degrees whose radiance
      spans 1e3 to 1e5 x the walls (fixed seeds), at elevations 12-70 degrees;
    - window: walls 0.05, a window of radiance 5 (100 : 1), by default 40 degrees wide from 5 to 35 degrees
      elevation, centred at azimuth 200 + rotation (``Lighting.window``);
    - sun: a blue sky (zenith 0.6 0.8 1.2, horizon 1.0 1.0 1.1), ground 0.3, and a 0.5-degree-radius sun of
      1e4 x the sky's mean radiance at 8 or 55 degrees elevation;
    - overcast: the CIE overcast sky, 1 at the zenith falling to 1/3 at the horizon ((1 + 2 sin elevation) / 3),
      ground 0.2: no source, no azimuthal detail (the same for every rotation);
    - hdri: the bundled HDRI (or a held-out one), upsampled by repetition, rotated by whole columns.
    """
    rot = float(rotation_deg)
    if light.family == "hdri":
        env, rot = _hdri(light.hdri, rot, h)
        return env.astype(np.float32), rot
    if light.family == "lamp":
        env = _sky(h, (0.05, 0.05, 0.06), (0.03, 0.03, 0.03), (0.01, 0.01, 0.01))
        add_disc(env, light.elevation_deg, 30.0 + rot, 1.0, (500.0, 480.0, 440.0))
    elif light.family == "room":
        n = int(light.name[-1])
        env = _sky(h, (0.01, 0.01, 0.01), (0.01, 0.01, 0.01), (0.005, 0.005, 0.005))
        rng = np.random.default_rng(n)
        powers = np.logspace(5, 3, n)  # 1e5 .. 1e3 x the walls
        for i, p in enumerate(powers):
            elev = rng.uniform(12, 70)
            az = 360.0 * i / n + rng.uniform(-20, 20) + rot
            tint = rng.uniform(0.85, 1.0, 3)
            add_disc(env, elev, az, 3.0, 0.01 * p * tint)
    elif light.family == "window":
        env = _sky(h, (0.05, 0.05, 0.05), (0.05, 0.05, 0.05), (0.03, 0.03, 0.03))
        theta, phi = _grid(h)
        elev = 90.0 - np.degrees(theta)
        lo, hi, width, az = light.window
        daz = (np.degrees(phi) - (az + rot) + 180.0) % 360.0 - 180.0
        win = (elev >= lo) & (elev <= hi) & (np.abs(daz) <= width / 2)
        env[win] = (5.0, 5.0, 5.2)
    elif light.family == "sun":
        env = _sky(h, (0.6, 0.8, 1.2), (1.0, 1.0, 1.1), (0.3, 0.3, 0.3))
        sky_mean = float(env[: h // 2].mean())
        add_disc(env, light.elevation_deg, 120.0 + rot, 0.5, (1e4 * sky_mean,) * 3)
    elif light.family == "overcast":
        theta, _ = _grid(h)
        up = np.clip(np.cos(theta), 0, 1)[..., None]  # sin elevation
        env = np.where(theta[..., None] < np.pi / 2, np.array([1.0, 1.0, 1.05]) * (1 + 2 * up) / 3,
                       np.array([0.2, 0.2, 0.2]))
    else:
        raise ValueError(f"unknown lighting family {light.family!r}")
    return env.astype(np.float32), rot
