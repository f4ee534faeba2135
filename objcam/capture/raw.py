"""Decode photos to LINEAR camera RGB: raws through rawpy (LibRaw), 16-bit linear TIFFs, and 8-bit JPEG/PNG views.

Units: a :class:`LinearImage` holds ``(raw - black) / (white - black)`` per CFA sample, i.e. units of the white
level (1.0 = saturation before white balance), then multiplied by the white-balance multipliers ``wb`` (ones when
no white balance is applied, the default). No gamma, no auto-brightening, no colour matrix: camera RGB.

Raw decoding, :func:`read_raw` ``demosaic=``:

- ``"superpixel"`` (default): each 2x2 CFA tile -> one RGB pixel (R, mean of the two greens, B). Half resolution;
  no interpolation, so the most radiometrically honest.
- ``"bilinear"``: full resolution; each channel is the normalised 3x3 bilinear average of its own CFA samples
  (own samples kept as they are). Exact on flat fields; edges get the usual bilinear colour fringes.
- ``"postprocess"``: LibRaw's own pipeline (AHD) with the settings that keep it linear and unscaled:
  ``gamma=(1, 1)``, ``no_auto_bright=True``, ``output_bps=16``, ``output_color=ColorSpace.raw``, unit
  ``user_wb`` (white balance is applied here afterwards, so LibRaw's highlight clip at 65535 never cuts a
  channel early), ``user_sat`` = white - black (LibRaw applies it after subtracting the black level: passing the
  white level itself darkens everything by black/white, 3% at 512/16383), ``user_black`` only when overridden, ``adjust_maximum_thr=0``
  (LibRaw otherwise lowers the white level to the data maximum), ``highlight_mode=Clip``. Output / 65535.
  LibRaw's defaults (sRGB gamma, auto-bright, daylight WB, adjusted maximum) change ratios by tens of percent.

Saturation mask: a pixel is saturated when any CFA sample that feeds it is at or above
``white - sat_margin * (white - black)`` (default margin 1% of the range).

Raws are oriented like LibRaw's ``postprocess`` (EXIF/DNG Orientation) unless ``orient=False``.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from objcam.errors import InputError

RAW_EXTENSIONS = frozenset({".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf",
                            ".rw2", ".pef", ".srw", ".3fr", ".fff", ".iiq", ".erf", ".mos", ".mef", ".mrw", ".kdc",
                            ".dcr", ".x3f", ".rwl", ".raw"})
TIFF_EXTENSIONS = frozenset({".tif", ".tiff"})
LDR_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png"})
DEMOSAIC_METHODS = ("superpixel", "bilinear", "postprocess")

UNREADABLE_FIX = "give a camera raw (DNG, CR2, NEF, ARW, ...), a 16-bit linear TIFF, or a JPEG/PNG; re-copy it " \
                 "from the camera if it is damaged"


@dataclass
class LinearImage:
    """A linear camera-RGB image (see the module doc for units) with its saturation mask."""

    rgb: np.ndarray  # float32 (H, W, 3)
    saturated: np.ndarray  # bool (H, W): some contributing sample at/near the white level
    path: Path
    wb: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))  # multipliers applied to rgb
    sensor_shape: tuple[int, int] = (0, 0)  # (rows, cols) before demosaicing, for bracket checks
    black_level: tuple[float, ...] = ()
    white_level: float = 1.0
    method: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        return self.rgb.shape[:2]


def _wb_vector(wb, raw=None, path: Path | None = None) -> np.ndarray:
    """None -> ones; "camera" -> the file's as-shot multipliers normalised to green = 1; else 3 (or 4) floats."""
    if wb is None:
        return np.ones(3, np.float32)
    if isinstance(wb, str):
        if wb != "camera":
            raise ValueError(f"wb must be None, 'camera' or three multipliers, got {wb!r}")
        if raw is None:
            raise InputError("this file has no camera white balance", path,
                             "give white-balance multipliers in capture.toml, or none")
        cam = np.asarray(raw.camera_whitebalance, dtype=np.float64)
        r, g, b = cam[0], cam[1], cam[2]
        if not (r > 0 and g > 0 and b > 0):
            raise InputError("the file's as-shot white balance is missing or zero", path,
                             "give white-balance multipliers in capture.toml, or none")
        return np.array([r / g, 1.0, b / g], np.float32)
    v = np.asarray(wb, dtype=np.float64).ravel()
    if v.size == 4:
        v = v[:3]
    if v.size != 3 or not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise InputError(f"white balance must be three positive multipliers, got {wb!r}", path,
                         "fix the white balance in capture.toml")
    return v.astype(np.float32)


@contextlib.contextmanager
def capture_c_stderr():
    """Collect what C libraries (LibRaw, OpenImageIO) print on file descriptor 2 while the block runs, so a bad
    file gives one clean error line instead of stray library chatter. Yields a list that receives the captured
    text when the block ends; the caller decides whether to echo it (:func:`_echo`) or fold it into an error."""
    out: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no real fd 2 (embedded interpreter): capture nothing
        yield out
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield out
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            out.append(tmp.read().decode("utf-8", "replace"))


def _libraw_complaint(text: str) -> str | None:
    """LibRaw's data-error callback prints these instead of failing; they mean damaged pixel data."""
    for line in text.splitlines():
        low = line.lower()
        if "unexpected end of file" in low or "corrupt data" in low:
            return line.split(": ", 1)[-1].strip() if ": " in line else line.strip()
    return None


def _open_raw(path: Path):
    import rawpy

    if not path.is_file():
        raise InputError("image not found", path, "check the path in capture.toml")
    with capture_c_stderr() as err:
        try:
            raw = rawpy.imread(str(path))  # NB: rawpy treats a non-str (e.g. a Path) as a file object
            bad = None
        except rawpy.LibRawFileUnsupportedError:
            bad = "not an image LibRaw can read (unsupported format, or not a raw file)"
        except (rawpy.LibRawError, OSError, ValueError) as e:
            bad = "file is empty" if path.stat().st_size == 0 else \
                f"cannot read raw: truncated or damaged header ({type(e).__name__})"
    if bad is not None:
        said = _libraw_complaint("".join(err))
        if said and "end of file" in said.lower():
            bad = "file is truncated"
        raise InputError(bad + (f" (LibRaw: {said})" if said else ""), path, UNREADABLE_FIX)
    _echo(err)
    return raw


def check_readable(path: Path) -> None:
    """InputError naming ``path`` unless it opens as an image of its kind (a raw's header parses; TIFF/JPEG/PNG
    decode). Used where a missing EXIF field would otherwise be reported for a file that is not an image."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext in RAW_EXTENSIONS:
        _open_raw(path).close()
    elif ext in TIFF_EXTENSIONS or ext in LDR_EXTENSIONS:
        import cv2

        _imread(path, cv2.IMREAD_UNCHANGED)


def _echo(err: list[str]) -> None:
    text = "".join(err)
    if text:
        sys.stderr.write(text)


def _raw_call(path: Path, fn):
    """Run ``fn()`` that unpacks/decodes raw data; LibRaw errors or data-error complaints (truncated or corrupt
    data) -> InputError naming the file."""
    import rawpy

    with capture_c_stderr() as err:
        try:
            result, exc = fn(), None
        except (rawpy.LibRawError, OSError, ValueError, RuntimeError) as e:
            result, exc = None, e
    said = _libraw_complaint("".join(err))
    if exc is not None or said:
        what = "truncated" if said and "end of file" in said.lower() else "corrupt or truncated"
        detail = f"LibRaw: {said}" if said else type(exc).__name__
        raise InputError(f"raw data is {what} ({detail})", path, UNREADABLE_FIX)
    _echo(err)
    return result


def _orient(img: np.ndarray, flip: int) -> np.ndarray:
    """Apply LibRaw's ``sizes.flip`` as ``postprocess`` does (dcraw's flip_index: bit 2 transposes, bit 1 flips
    rows, bit 0 flips columns; 3 = 180, 5 = 90 CCW, 6 = 90 CW)."""
    if flip & 2:
        img = img[::-1]
    if flip & 1:
        img = img[:, ::-1]
    if flip & 4:
        img = img.swapaxes(0, 1)
    return img


def _cfa_channel_map(raw, path: Path) -> np.ndarray:
    """Raw colour index (0..3) -> RGB channel (0..2) from ``color_desc`` (e.g. b'RGBG')."""
    desc = raw.color_desc.decode("ascii", "replace")
    lut = {"R": 0, "G": 1, "B": 2}
    if any(ch not in lut for ch in desc):
        raise InputError(f"sensor colours {desc!r} are not RGB", path, "convert the raw to a 16-bit linear TIFF")
    return np.array([lut[ch] for ch in desc], np.int64)


def _bilinear(values: np.ndarray, chan: np.ndarray) -> np.ndarray:
    """Normalised-convolution bilinear demosaic: per channel, sum(k * v * mask) / sum(k * mask) over a 3x3
    kernel (1 2 1; 2 4 2; 1 2 1), own samples kept. Exact on flat fields for Bayer and X-Trans layouts."""
    import cv2

    k = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32)
    h, w = values.shape
    out = np.empty((h, w, 3), np.float32)
    for c in range(3):
        m = (chan == c).astype(np.float32)
        num = cv2.filter2D(values * m, -1, k, borderType=cv2.BORDER_CONSTANT)
        den = cv2.filter2D(m, -1, k, borderType=cv2.BORDER_CONSTANT)
        if np.any(den <= 0):
            raise ValueError("CFA layout leaves a 3x3 window without a sample of some colour")
        out[..., c] = np.where(m > 0, values, num / den)
    return out


def _superpixel(values: np.ndarray, chan: np.ndarray, sat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h, w = (values.shape[0] // 2) * 2, (values.shape[1] // 2) * 2
    values, chan, sat = values[:h, :w], chan[:h, :w], sat[:h, :w]
    tile = chan[:2, :2]
    if sorted(set(tile.ravel().tolist())) != [0, 1, 2] or not np.array_equal(np.tile(tile, (h // 2, w // 2)), chan):
        raise ValueError("superpixel needs a 2x2 Bayer layout")
    out = np.zeros((h // 2, w // 2, 3), np.float32)
    cnt = np.zeros(3, np.float32)
    for dy in range(2):
        for dx in range(2):
            c = tile[dy, dx]
            out[..., c] += values[dy::2, dx::2]
            cnt[c] += 1
    out /= cnt
    s = sat[0::2, 0::2] | sat[0::2, 1::2] | sat[1::2, 0::2] | sat[1::2, 1::2]
    return out, s


def read_raw(path: str | Path, *, demosaic: str = "superpixel", wb=None, sat_margin: float = 0.01,
             black_level: float | Sequence[float] | None = None, white_level: float | None = None,
             orient: bool = True) -> LinearImage:
    """Decode a camera raw to linear camera RGB in white-level units (see the module doc).

    ``wb``: None (no white balance, default), ``"camera"`` (the file's as-shot multipliers, green = 1) or three
    multipliers (R, G, B). ``black_level`` (one value or four per raw colour) / ``white_level`` override the
    file's (e.g. from capture.toml). Raises InputError naming the file for unreadable, corrupt or truncated data.
    """
    import rawpy

    path = Path(path)
    if demosaic not in DEMOSAIC_METHODS:
        raise ValueError(f"demosaic must be one of {DEMOSAIC_METHODS}, got {demosaic!r}")
    raw = _open_raw(path)
    with raw:
        cmap = _cfa_channel_map(raw, path)
        mosaic = _raw_call(path, lambda: np.array(raw.raw_image_visible, dtype=np.float32))
        colors = _raw_call(path, lambda: np.array(raw.raw_colors_visible))
        if mosaic.size == 0:
            raise InputError("raw has no pixels", path, UNREADABLE_FIX)
        blacks = np.asarray(raw.black_level_per_channel, np.float64) if black_level is None else \
            np.broadcast_to(np.asarray(black_level, np.float64), (4,)).copy()
        if blacks.min() >= 16:  # exact zeros far below a real black level: zero-filled (damaged) data
            n0 = int(np.count_nonzero(mosaic == 0))
            if n0 > 0.001 * mosaic.size:
                raise InputError(f"raw data looks corrupt: {n0} samples are 0, far below the black level "
                                 f"{blacks.min():g}", path, UNREADABLE_FIX)
        wl_file = raw.camera_white_level_per_channel
        if white_level is not None:
            white = float(white_level)
        elif wl_file is not None and all(w > 0 for w in wl_file):
            white = float(min(wl_file))
        else:
            white = float(raw.white_level)
        if not (white > blacks.max()):
            raise InputError(f"white level {white:g} is not above the black level {blacks.max():g}", path,
                             "give black_level/white_level in capture.toml")
        wbv = _wb_vector(wb, raw, path)
        black_px = blacks[colors].astype(np.float32)
        span_px = (white - black_px).astype(np.float32)
        sat_raw = mosaic >= (white - sat_margin * span_px)
        chan = cmap[colors]
        flip = raw.sizes.flip if orient else 0

        if demosaic == "postprocess":
            # LibRaw compares user_sat with the data AFTER subtracting the common black level (the minimum over
            # channels): passing the white level itself scales everything by (white - black) / white.
            base = float(blacks.min())
            kw = dict(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=False, use_auto_wb=False,
                      user_wb=[1.0, 1.0, 1.0, 1.0], output_color=rawpy.ColorSpace.raw,
                      user_sat=int(round(white - base)), adjust_maximum_thr=0.0,
                      highlight_mode=rawpy.HighlightMode.Clip, bright=1.0, user_flip=flip)
            if black_level is not None:
                kw.update(user_black=int(round(base)), user_cblack=[int(round(b - base)) for b in blacks])
            out16 = _raw_call(path, lambda: raw.postprocess(**kw))
            # LibRaw divides every channel by (white - common black); rescale to each channel's own span.
            fix = np.array([np.mean([(white - base) / (white - blacks[i]) for i in range(len(cmap)) if cmap[i] == c]
                                    or [1.0]) for c in range(3)], np.float32)
            rgb = out16.astype(np.float32) / 65535.0 * fix
            import cv2

            sat = cv2.dilate(sat_raw.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            sat = _orient(sat, flip) | np.any(out16 >= 65535, axis=2)
        else:
            lin = (mosaic - black_px) / span_px
            if demosaic == "superpixel":
                try:
                    rgb, sat = _superpixel(lin, chan, sat_raw)
                except ValueError as e:
                    raise InputError(str(e), path, "use demosaic = \"bilinear\" or \"postprocess\"") from None
            else:
                import cv2

                try:
                    rgb = _bilinear(lin, chan)
                except ValueError as e:
                    raise InputError(str(e), path, "use demosaic = \"postprocess\"") from None
                sat = cv2.dilate(sat_raw.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            rgb, sat = _orient(rgb, flip), _orient(sat, flip)
        rgb = np.ascontiguousarray(rgb * wbv, dtype=np.float32)
        return LinearImage(rgb=rgb, saturated=np.ascontiguousarray(sat), path=path, wb=wbv,
                           sensor_shape=tuple(int(x) for x in mosaic.shape),
                           black_level=tuple(float(b) for b in blacks), white_level=white, method=demosaic)


def _imread(path: Path, flags: int) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise InputError("image not found", path, "check the path in capture.toml")
    data = np.fromfile(path, np.uint8)
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None or img.size == 0:
        raise InputError("not an image that can be decoded (corrupt, truncated or unknown format)", path,
                         UNREADABLE_FIX)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3]
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return np.ascontiguousarray(img[..., ::-1])  # BGR -> RGB


def read_tiff16(path: str | Path, *, sat_margin: float = 0.01, wb=None) -> LinearImage:
    """A linear TIFF (e.g. ``dcraw -4 -T`` or a linear export): 16-bit -> value / 65535 (saturation at
    65535 * (1 - sat_margin)); 32-bit float -> as is, nothing flagged saturated. 8-bit -> InputError."""
    import cv2

    path = Path(path)
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    wbv = _wb_vector(wb, None, path)
    if img.dtype == np.uint16:
        rgb = img.astype(np.float32) / 65535.0
        sat = np.any(img >= 65535 * (1.0 - sat_margin), axis=2)
        white = 65535.0
    elif img.dtype == np.float32:
        rgb, sat, white = img.astype(np.float32), np.zeros(img.shape[:2], bool), 1.0
    else:
        raise InputError(f"{img.dtype.itemsize * 8}-bit TIFF is not linear", path,
                         "export a 16-bit linear TIFF, or give the raw file")
    return LinearImage(rgb=np.ascontiguousarray(rgb * wbv), saturated=sat, path=path, wb=wbv,
                       sensor_shape=tuple(img.shape[:2]), black_level=(0.0,), white_level=white, method="tiff")


def read_ldr(path: str | Path) -> np.ndarray:
    """An 8-bit display-referred view (JPEG/PNG) as uint8 (H, W, 3) RGB, EXIF orientation applied. Not linear:
    linearise with a response curve (:func:`objcam.capture.hdr.apply_response`)."""
    import cv2

    return _imread(Path(path), cv2.IMREAD_COLOR)


def read_linear(path: str | Path, **kw) -> LinearImage:
    """Dispatch on the extension: raws -> :func:`read_raw` (``kw`` passed on), TIFF -> :func:`read_tiff16`.
    JPEG/PNG are not linear: InputError (merge them with :func:`objcam.capture.hdr.merge_ldr_bracket`)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext in TIFF_EXTENSIONS:
        return read_tiff16(path, **{k: v for k, v in kw.items() if k in ("sat_margin", "wb")})
    if ext in LDR_EXTENSIONS:
        raise InputError("JPEG/PNG is not linear", path,
                         "give raws, or an exposure bracket of JPEGs so a response curve can be recovered")
    return read_raw(path, **kw)
