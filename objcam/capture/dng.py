"""Write Bayer-mosaiced DNGs from linear RGB for synthetic captures (PiDNG), read back like a camera's file.

:func:`write_dng` takes a linear camera-RGB *signal* in units of the white level (1.0 = saturation, after black
subtraction), i.e. the exposure is already applied; ``exposure_time`` etc. are metadata. :func:`synth_bracket`
writes a bracket from one radiance map: frame ``k`` gets signal ``radiance * times[k]`` (so ``radiance`` is in
white-level units per second).

The file is an uncompressed 16-bit RGGB CFA DNG: BlackLevel (2x2 repeat), WhiteLevel, AsShotNeutral (= 1 / the
white-balance multipliers, green = 1), an identity ColorMatrix1, Make/Model/UniqueCameraModel in IFD0, and
ExposureTime/FNumber/ISOSpeedRatings in a real EXIF sub-IFD (tag 0x8769), where exifread ("EXIF ExposureTime")
and LibRaw (``rawpy.other``) both find them. (PiDNG's own recipe puts them in IFD0, where LibRaw does not look:
``other.iso_speed`` then reads 0; and PiDNG's IFD-typed tag is broken, see ``_sub_ifd_tag_class``.)
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Sequence

import numpy as np

from objcam.image_io import atomic_write_bytes

#: CFA layouts as (row, col) offsets of R, G1, G2, B within the 2x2 tile, and the DNG CFAPattern codes.
_CFA = {
    "RGGB": ([0, 1, 1, 2], {(0, 0): 0, (0, 1): 1, (1, 0): 1, (1, 1): 2}),
    "BGGR": ([2, 1, 1, 0], {(0, 0): 2, (0, 1): 1, (1, 0): 1, (1, 1): 0}),
    "GRBG": ([1, 0, 2, 1], {(0, 0): 1, (0, 1): 0, (1, 0): 2, (1, 1): 1}),
    "GBRG": ([1, 2, 0, 1], {(0, 0): 1, (0, 1): 2, (1, 0): 0, (1, 1): 1}),
}


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise for synthetic raws, in electrons.

    ``full_well_e`` electrons fill the range black..white at ``base_iso``; at ISO ``iso`` the range holds
    ``full_well_e * base_iso / iso`` electrons (gain). Photon shot noise is Poisson in electrons, read noise is
    Gaussian (``read_noise_e`` electrons rms, after gain); the result is rounded to integer DN (quantisation) and
    clipped to [0, WhiteLevel].
    """

    full_well_e: float = 50000.0
    read_noise_e: float = 3.0
    base_iso: float = 100.0
    seed: int | None = 0


def _rational(x: float, max_den: int = 1_000_000) -> list[int]:
    f = Fraction(float(x)).limit_denominator(max_den)
    return [f.numerator, f.denominator]


def mosaic(rgb: np.ndarray, cfa: str = "RGGB") -> np.ndarray:
    """(H, W, 3) -> (H, W) CFA mosaic: each site keeps its own colour's value (H and W must be even)."""
    h, w, _ = rgb.shape
    out = np.empty((h, w), dtype=rgb.dtype)
    for (dy, dx), c in _CFA[cfa][1].items():
        out[dy::2, dx::2] = rgb[dy::2, dx::2, c]
    return out


def raw_counts(signal: np.ndarray, *, black_level: int, white_level: int, iso: float = 100.0,
               noise: NoiseModel | None = None, cfa: str = "RGGB") -> np.ndarray:
    """Linear signal (H, W, 3) in white-level units -> uint16 CFA counts with optional noise, quantised and
    clipped at the white level."""
    sig = np.asarray(signal, dtype=np.float64)
    if sig.ndim != 3 or sig.shape[2] != 3:
        raise ValueError(f"signal must be (H, W, 3), got {sig.shape}")
    if sig.shape[0] % 2 or sig.shape[1] % 2:
        raise ValueError(f"a Bayer mosaic needs an even height and width, got {sig.shape[:2]}")
    if cfa not in _CFA:
        raise ValueError(f"cfa must be one of {sorted(_CFA)}")
    mos = np.clip(mosaic(sig, cfa), 0.0, None)
    span = float(white_level - black_level)
    if noise is not None:
        rng = np.random.default_rng(noise.seed)
        well = noise.full_well_e * noise.base_iso / float(iso)
        electrons = rng.poisson(mos * well).astype(np.float64)
        electrons += rng.normal(0.0, noise.read_noise_e, size=electrons.shape)
        mos = electrons / well
    dn = np.rint(black_level + mos * span)
    return np.clip(dn, 0, white_level).astype(np.uint16)


def write_dng(path: str | Path, signal: np.ndarray, *, exposure_time: float, iso: float = 100.0,
              f_number: float = 8.0, make: str = "objcam", model: str = "synthetic",
              black_level: int = 512, white_level: int = 16383,
              wb: Sequence[float] = (2.0, 1.0, 1.5), noise: NoiseModel | None = None,
              cfa: str = "RGGB", focal_length_mm: float | None = None) -> Path:
    """Write ``signal`` (H, W, 3 linear camera RGB, white-level units: 0 = black, 1 = saturation) as a 16-bit CFA
    DNG, atomically. ``wb``: the as-shot white-balance multipliers (R, G, B), stored as AsShotNeutral = 1 / wb
    (rawpy's ``camera_whitebalance`` then returns ``wb``). ``focal_length_mm``: optional EXIF FocalLength (the zoom
    setting). Returns the path."""
    from pidng.core import RAW2DNG
    from pidng.defs import CalibrationIlluminant, Orientation, PhotometricInterpretation
    from pidng.dng import DNGTags, Tag, dngIFD, dngTag

    if not (0 <= black_level < white_level <= 65535):
        raise ValueError("need 0 <= black_level < white_level <= 65535")
    if exposure_time <= 0:
        raise ValueError("exposure_time must be > 0")
    counts = raw_counts(signal, black_level=black_level, white_level=white_level, iso=iso, noise=noise, cfa=cfa)
    h, w = counts.shape
    if min(h, w) < 22:
        raise ValueError("LibRaw refuses raws under 22 pixels a side (LibRawFileUnsupportedError)")
    if max(h, w) > 65535:
        raise ValueError("PiDNG stores the tile size as SHORT: at most 65535 pixels a side")

    t = DNGTags()
    t.set(Tag.ImageWidth, w)
    t.set(Tag.ImageLength, h)
    t.set(Tag.TileWidth, w)  # PiDNG always writes one tile holding the whole image
    t.set(Tag.TileLength, h)
    t.set(Tag.Orientation, Orientation.Horizontal)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    t.set(Tag.BitsPerSample, 16)
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, _CFA[cfa][0])
    t.set(Tag.BlackLevelRepeatDim, [2, 2])
    t.set(Tag.BlackLevel, [int(black_level)] * 4)
    t.set(Tag.WhiteLevel, int(white_level))
    one, zero = [1, 1], [0, 1]
    t.set(Tag.ColorMatrix1, [one, zero, zero, zero, one, zero, zero, zero, one])
    t.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    wb = np.asarray(wb, dtype=np.float64)
    if wb.shape != (3,) or np.any(wb <= 0):
        raise ValueError("wb must be three positive multipliers")
    t.set(Tag.AsShotNeutral, [_rational(wb[1] / c) for c in wb])
    t.set(Tag.Make, str(make))
    t.set(Tag.Model, str(model))
    t.set(Tag.UniqueCameraModel, f"{make} {model}")
    # NB: PiDNG adds DNGVersion/DNGBackwardVersion itself; setting them here would duplicate the tags.

    exif = dngIFD()
    exif.tags += [dngTag(Tag.ExposureTime, [_rational(exposure_time)]),
                  dngTag(Tag.FNumber, [_rational(f_number, 1000)]),
                  dngTag(Tag.PhotographicSensitivity, [int(round(iso))]),
                  dngTag(Tag.ExifVersion, list(b"0231"))]
    if focal_length_mm is not None:
        exif.tags.append(dngTag(Tag.FocalLength, [_rational(focal_length_mm, 1000)]))
    t.__tags__[Tag.EXIF_IFD] = _sub_ifd_tag_class()(Tag.EXIF_IFD, [exif])

    conv = RAW2DNG()
    conv.options(t, path="", compress=False)
    buf = conv.convert(np.ascontiguousarray(counts))
    path = Path(path)
    atomic_write_bytes(path, bytes(buf))
    return path


def synth_bracket(folder: str | Path, radiance: np.ndarray, times: Sequence[float], *, stem: str = "frame",
                  noise: NoiseModel | None = None, **kw) -> list[Path]:
    """Write one DNG per exposure time: frame k holds ``radiance * times[k]`` (white-level units). Noise seeds
    differ per frame (``noise.seed + k``). Extra keywords go to :func:`write_dng`."""
    folder = Path(folder)
    paths = []
    for k, t in enumerate(times):
        nk = None if noise is None else NoiseModel(noise.full_well_e, noise.read_noise_e, noise.base_iso,
                                                   None if noise.seed is None else noise.seed + k)
        paths.append(write_dng(folder / f"{stem}_{k:02d}.dng", np.asarray(radiance) * float(t),
                               exposure_time=float(t), noise=nk, **kw))
    return paths


def _sub_ifd_tag_class():
    from pidng.dng import Type, dngTag

    class _SubIFDTag(dngTag):
        """PiDNG 4.0.9's IFD-typed tag concatenates str and bytes in ``setValue`` (TypeError); the rest of its
        sub-IFD plumbing (offsets, ``write``) works, so only the value is fixed here."""

        def setValue(self, value):
            if self.DataType == Type.IFD:
                self.Value = b"\0\0\0\0"
                self.subIFD = value[0]
            else:
                super().setValue(value)

    return _SubIFDTag

