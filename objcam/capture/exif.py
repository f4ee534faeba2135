"""Exposure metadata (exposure time, ISO, f-number, make/model) from a photo's EXIF.

Read with exifread (``process_file(details=False)``: no maker notes), from the EXIF sub-IFD first and IFD0 second
(TIFF/EP and PiDNG put them there):

- exposure time: ``EXIF ExposureTime`` / ``Image ExposureTime`` (0x829A), else APEX ``ShutterSpeedValue``
  (0x9201, t = 2^-Tv)
- f-number: ``FNumber`` (0x829D), else APEX ``ApertureValue`` (0x9202, N = 2^(Av/2))
- ISO: ``ISOSpeedRatings`` (0x8827, a.k.a. PhotographicSensitivity), else ``RecommendedExposureIndex`` (0x8832)
- camera: ``Image Make`` (0x010F), ``Image Model`` (0x0110)
- focal length: ``FocalLength`` (0x920A), millimetres (tells zoom settings apart)

When exifread finds no exposure time (a format it does not parse, e.g. some CR3/RAF), OpenImageIO's reader
(LibRaw for raws) is asked for ``ExposureTime``, ``FNumber``, ``Exif:ISOSpeedRatings``, ``Make``, ``Model``.
rawpy's ``other.iso_speed``/``shutter_speed`` are not used: they read 0 for files whose EXIF sits in IFD0.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

from objcam.errors import InputError

MISSING_EXPOSURE_FIX = ("shoot with EXIF on, or give [camera] exposure_time = SECONDS in capture.toml (every photo "
                        "without EXIF; exposure_times = {\"NAME\" = SECONDS} per file)")


@dataclass(frozen=True)
class ExposureInfo:
    """Exposure settings of one photo. ``None`` where the file does not say."""

    exposure_time: float | None  # seconds
    iso: float | None
    f_number: float | None
    make: str | None
    model: str | None
    source: str  # "exifread", "oiio", or "none"
    focal_length: float | None = None  # millimetres

    @property
    def camera(self) -> str:
        return " ".join(x for x in (self.make, self.model) if x) or "unknown camera"


def _num(tag) -> float | None:
    """First value of an exifread tag as a float (None if absent, zero-denominator or not finite)."""
    if tag is None:
        return None
    vals = getattr(tag, "values", None)
    v = vals[0] if isinstance(vals, (list, tuple)) and vals else vals
    try:
        x = float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def _str(tag) -> str | None:
    if tag is None:
        return None
    s = str(getattr(tag, "values", tag)).strip().strip("\x00").strip()
    return s or None


def _first(tags: dict, *names: str):
    for n in names:
        for prefix in ("EXIF ", "Image "):
            if prefix + n in tags:
                return tags[prefix + n]
    return None


def _from_exifread(path: Path) -> ExposureInfo | None:
    import exifread

    log = logging.getLogger("exifread")
    level = log.level
    log.setLevel(logging.CRITICAL)  # it logs warnings ("Unexpected slice length") for damaged or odd files
    try:
        with open(path, "rb") as f:
            tags = exifread.process_file(f, details=False, extract_thumbnail=False)
    except Exception:  # exifread raises assorted errors on formats it does not know
        return None
    finally:
        log.setLevel(level)
    if not tags:
        return None
    t = _num(_first(tags, "ExposureTime"))
    if not t or t <= 0:
        tv = _num(_first(tags, "ShutterSpeedValue"))
        t = 2.0 ** (-tv) if tv is not None else None
    n = _num(_first(tags, "FNumber"))
    if not n or n <= 0:
        av = _num(_first(tags, "ApertureValue"))
        n = 2.0 ** (av / 2.0) if av is not None else None
    iso = _num(_first(tags, "ISOSpeedRatings", "PhotographicSensitivity", "RecommendedExposureIndex"))
    f = _num(_first(tags, "FocalLength"))
    return ExposureInfo(exposure_time=t if t and t > 0 else None, iso=iso if iso and iso > 0 else None,
                        f_number=n if n and n > 0 else None, make=_str(tags.get("Image Make")),
                        model=_str(tags.get("Image Model")), source="exifread",
                        focal_length=f if f and f > 0 else None)


def _from_oiio(path: Path) -> ExposureInfo | None:
    try:
        import OpenImageIO as oiio
    except ImportError:
        return None
    from objcam.capture.raw import capture_c_stderr

    with capture_c_stderr():  # its raw plugin prints "File format not recognized." for non-images
        inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        return None
    try:
        spec = inp.spec()

        def get(*names):
            for nm in names:
                v = spec.getattribute(nm)
                if v is not None:
                    return v[0] if isinstance(v, (tuple, list)) else v
            return None

        t, n, iso = get("ExposureTime", "Exif:ExposureTime"), get("FNumber", "Exif:FNumber"), \
            get("Exif:ISOSpeedRatings", "Exif:PhotographicSensitivity")
        make, model = get("Make"), get("Model")
        focal = get("FocalLength", "Exif:FocalLength")
    finally:
        inp.close()

    def pos(x):
        try:
            x = float(x)
        except (TypeError, ValueError):
            return None
        return x if math.isfinite(x) and x > 0 else None

    return ExposureInfo(exposure_time=pos(t), iso=pos(iso), f_number=pos(n), make=(str(make).strip() or None)
                        if make else None, model=(str(model).strip() or None) if model else None, source="oiio",
                        focal_length=pos(focal))


def read_exif(path: str | Path) -> ExposureInfo:
    """Exposure settings of ``path`` (fields ``None`` where absent). Raises InputError if the file is missing."""
    path = Path(path)
    if not path.is_file():
        raise InputError("image not found", path, "check the path in capture.toml")
    info = _from_exifread(path)
    if info is None or info.exposure_time is None:
        alt = _from_oiio(path)
        if alt is not None and (info is None or alt.exposure_time is not None):
            info = alt
    return info or ExposureInfo(None, None, None, None, None, "none")


def exposure_time(path: str | Path, override: float | None = None) -> float:
    """Exposure time in seconds: ``override`` (from capture.toml) if given, else the file's EXIF; a missing one is
    an InputError naming the file."""
    if override is not None:
        if not (override > 0 and math.isfinite(override)):
            raise InputError(f"exposure time must be a positive number of seconds, got {override!r}", path,
                             "fix the exposure time in capture.toml")
        return float(override)
    t = read_exif(path).exposure_time
    if t is None:
        from objcam.capture.raw import check_readable

        check_readable(Path(path))  # a file that is no image at all has no EXIF either: say that first
        raise InputError("no exposure time in the EXIF", path, MISSING_EXPOSURE_FIX)
    return t
