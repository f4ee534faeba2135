"""Merge an exposure bracket into one linear HDR image.

Raw (or linear TIFF) brackets, :func:`merge_raw_bracket` / :func:`merge_frames`, in raw-linear camera RGB:

- each frame k (exposure time t_k) estimates radiance as ``value_k * t_ref / t_k``;
- weights are proportional to t_k (shot-noise-limited inverse variance of that estimate; measured better here
  than hat weights on the pixel value), and zero where the pixel's brightest channel (before white balance) is
  above ``high`` (default 0.9 of the white level) or below ``low`` (default 0.002), or the saturation mask is set;
- pixels with no usable frame take the frame with the largest unsaturated signal (very dark pixels: the longest
  frame); pixels saturated in EVERY frame take the shortest frame's value (a lower bound, never silently
  clipped), are flagged ``valid = False`` and counted in ``n_invalid``.

Units (``units=``): ``"reference"`` (default): units of the longest exposure, i.e. the value the longest frame
would record if it had no white level (1.0 = its saturation level times the white-balance multiplier);
``"per_second"``: white-level units per second of exposure (``value / t``). ``MergeResult.units`` says which.

JPEG/PNG brackets, :func:`merge_ldr_bracket`: OpenCV's Debevec calibration recovers the camera response
(``cv2.createCalibrateDebevec``), ``cv2.createMergeDebevec`` merges. OpenCV normalises the response so that
pixel value 128 maps to 1, so the result is RELATIVE radiance: ``"per_second"`` = response-linearised value per
second, ``"reference"`` = times the longest exposure (a mid-grey 128 in the longest frame reads about 1). The
absolute scale and the white balance are those of the camera's JPEG engine: compare ratios only.

The bracket must be one camera, one sensor size, one aperture and one ISO (times may come from capture.toml);
frames are assumed registered (tripod), no alignment is done.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from objcam.capture.exif import ExposureInfo, exposure_time, read_exif
from objcam.capture.raw import LinearImage, read_ldr, read_linear
from objcam.errors import InputError
from objcam.progress import bar

UNITS = ("reference", "per_second")


@dataclass
class MergeResult:
    radiance: np.ndarray  # float32 (H, W, 3), see ``units``
    valid: np.ndarray  # bool (H, W): False where every frame was saturated (value is a lower bound)
    n_invalid: int  # count of pixels saturated in every frame
    n_fallback: int  # pixels with no frame inside [low, high], filled from the best unsaturated frame
    frames_used: np.ndarray  # uint8 (H, W): frames with nonzero weight per pixel
    times: tuple[float, ...]  # exposure times, ascending
    paths: tuple[Path, ...]  # in the same order
    units: str  # "reference" or "per_second"
    reference_time: float  # radiance = value * reference_time / t  (1.0 for per_second)
    wb: np.ndarray  # white-balance multipliers in the data (ones = none)

    def summary(self) -> str:
        n = self.valid.size
        return (f"merged {len(self.times)} frames ({self.times[0]:.4g}..{self.times[-1]:.4g} s), "
                f"units={self.units}; {self.n_invalid} of {n} pixels saturated in every frame (flagged invalid, "
                f"filled from the shortest frame), {self.n_fallback} from a single out-of-range frame")


class _Accumulator:
    """Streams frames (ascending exposure time) into the weighted merge without holding them all."""

    def __init__(self, t_ref: float, low: float, high: float, weighting: str):
        if not (0.0 <= low < high <= 1.0):
            raise ValueError("need 0 <= low < high <= 1")
        if weighting not in ("time", "hat"):
            raise ValueError("weighting must be 'time' or 'hat'")
        self.t_ref, self.low, self.high, self.weighting = t_ref, low, high, weighting
        self.num = self.den = self.used = None
        self.best_m = self.best_val = self.shortest = self.all_sat = None

    def add(self, img: LinearImage, t: float) -> None:
        rgb = img.rgb.astype(np.float32)
        m = np.max(rgb / img.wb, axis=2)  # brightest channel in white-level units, before white balance
        scaled = rgb * np.float32(self.t_ref / t)
        ok = (m > self.low) & (m < self.high) & ~img.saturated
        if self.weighting == "time":
            w = np.where(ok, np.float32(t), np.float32(0))
        else:  # hat on the pixel value, peak at the middle of [low, high]
            mid, half = (self.low + self.high) / 2, (self.high - self.low) / 2
            w = np.where(ok, np.clip(1.0 - np.abs(m - mid) / half, 1e-3, None), 0).astype(np.float32)
        if self.num is None:
            self.num = np.zeros_like(scaled)
            self.den = np.zeros(m.shape, np.float32)
            self.used = np.zeros(m.shape, np.uint8)
            self.best_m = np.full(m.shape, -np.inf, np.float32)
            self.best_val = scaled.copy()
            self.shortest = scaled.copy()
            self.all_sat = np.ones(m.shape, bool)
        self.num += scaled * w[..., None]
        self.den += w
        self.used += ok
        better = ~img.saturated & (m > self.best_m)
        self.best_m = np.where(better, m, self.best_m)
        self.best_val[better] = scaled[better]
        self.all_sat &= img.saturated

    def result(self):
        have = self.den > 0
        rad = np.where(have[..., None], self.num / np.maximum(self.den, 1e-30)[..., None], self.best_val)
        rad[self.all_sat] = self.shortest[self.all_sat]
        n_fallback = int(np.count_nonzero(~have & ~self.all_sat))
        return rad.astype(np.float32), ~self.all_sat, int(np.count_nonzero(self.all_sat)), n_fallback, self.used


def _check_times(times: Sequence[float], paths: Sequence[Path]) -> None:
    for t, p in zip(times, paths):
        if not (t > 0 and math.isfinite(t)):
            raise InputError(f"exposure time must be a positive number of seconds, got {t!r}", p,
                             "fix the exposure time in capture.toml")


def _check_same(infos: Sequence[ExposureInfo], paths: Sequence[Path]) -> None:
    """One camera, one aperture, one ISO across the bracket (fields the files do not give are not compared)."""
    def differ(a, b, rel=0.0):
        return a is not None and b is not None and abs(a - b) > rel * max(abs(a), abs(b))

    for field, what, fix, rel in (
            ("camera", "cameras", "shoot the whole bracket with one camera", None),
            ("f_number", "apertures", "bracket with the shutter speed only (fixed aperture)", 0.02),
            ("iso", "ISO settings", "bracket with the shutter speed only (fixed ISO, auto-ISO off)", 0.02)):
        ref_i = next((i for i, inf in enumerate(infos) if getattr(inf, field if field != "camera" else "make")),
                     None)
        if ref_i is None:
            continue
        for i, inf in enumerate(infos):
            if field == "camera":
                bad = inf.make is not None and (inf.make, inf.model) != (infos[ref_i].make, infos[ref_i].model)
                va, vb = infos[ref_i].camera, inf.camera
            else:
                va, vb = getattr(infos[ref_i], field), getattr(inf, field)
                bad = differ(va, vb, rel)
            if bad:
                raise InputError(f"bracket mixes {what}: {va} ({paths[ref_i].name}) and {vb} ({paths[i].name})",
                                 paths[i], fix)


def _check_shapes(shape_a, shape_b, path_a: Path, path_b: Path, what: str = "image size") -> None:
    if tuple(shape_a) != tuple(shape_b):
        sa, sb = "x".join(map(str, shape_a[::-1])), "x".join(map(str, shape_b[::-1]))
        raise InputError(f"bracket mixes {what}s: {sa} ({path_a.name}) and {sb} ({path_b.name})", path_b,
                         "use frames from one camera at one image size")


def merge_frames(frames: Sequence[LinearImage], times: Sequence[float], *, low: float = 0.002,
                 high: float = 0.9, weighting: str = "time", units: str = "reference") -> MergeResult:
    """Merge already-decoded linear frames (any order) with their exposure times (see the module doc)."""
    if len(frames) != len(times) or not frames:
        raise ValueError("need one exposure time per frame, and at least one frame")
    if units not in UNITS:
        raise ValueError(f"units must be one of {UNITS}")
    paths = [f.path for f in frames]
    _check_times(times, paths)
    for f in frames[1:]:
        _check_shapes(frames[0].shape, f.shape, frames[0].path, f.path)
        if not np.allclose(f.wb, frames[0].wb):
            raise InputError("bracket frames have different white balance", f.path,
                             "decode every frame with the same white-balance multipliers")
    order = np.argsort(np.asarray(times, np.float64), kind="stable")
    ts = [float(times[i]) for i in order]
    t_ref = ts[-1] if units == "reference" else 1.0
    acc = _Accumulator(t_ref, low, high, weighting)
    for i in order:
        acc.add(frames[i], float(times[i]))
    rad, valid, n_inv, n_fb, used = acc.result()
    return MergeResult(rad, valid, n_inv, n_fb, used, tuple(ts), tuple(paths[i] for i in order), units, t_ref,
                       np.asarray(frames[0].wb, np.float32))


def _resolve_times(paths: Sequence[Path], times: Sequence[float | None] | None) -> list[float]:
    if times is not None and len(times) != len(paths):
        raise InputError(f"{len(times)} exposure times for {len(paths)} frames", paths[0],
                         "give one exposure time per frame in capture.toml")
    return [exposure_time(p, None if times is None else times[i]) for i, p in enumerate(paths)]


def merge_raw_bracket(paths: Sequence[str | Path], times: Sequence[float | None] | None = None, *,
                      demosaic: str = "superpixel", wb=None, low: float = 0.002, high: float = 0.9,
                      weighting: str = "time", units: str = "reference", sat_margin: float = 0.01,
                      black_level=None, white_level=None) -> MergeResult:
    """Read a bracket of raws (or 16-bit linear TIFFs) and merge it, streaming one frame at a time.

    ``times``: per-frame exposure times in seconds overriding EXIF (None entries: from EXIF). ``wb="camera"``
    uses the LONGEST frame's as-shot multipliers for every frame. Other keywords: :func:`read_raw`,
    :func:`merge_frames`. Errors (InputError naming the file): unreadable/corrupt frames, missing exposure time,
    mixed cameras, apertures, ISOs or image sizes.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("empty bracket")
    if units not in UNITS:
        raise ValueError(f"units must be one of {UNITS}")
    for p in paths:
        if not p.is_file():
            raise InputError("image not found", p, "check the path in capture.toml")
    ts = _resolve_times(paths, times)
    _check_times(ts, paths)
    _check_same([read_exif(p) for p in paths], paths)
    order = sorted(range(len(paths)), key=lambda i: ts[i])
    t_ref = ts[order[-1]] if units == "reference" else 1.0
    kw = dict(demosaic=demosaic, sat_margin=sat_margin, black_level=black_level, white_level=white_level)
    first: LinearImage | None = None
    if isinstance(wb, str) and wb == "camera":
        first = read_linear(paths[order[-1]], wb="camera", **kw)
        wb = first.wb
    acc = _Accumulator(t_ref, low, high, weighting)
    ref_img = None
    for i in bar(order, desc="merge bracket", unit="frame"):
        img = first if (first is not None and i == order[-1]) else read_linear(paths[i], wb=wb, **kw)
        if ref_img is None:
            ref_img = img
        else:
            _check_shapes(ref_img.sensor_shape, img.sensor_shape, ref_img.path, img.path, "sensor size")
            _check_shapes(ref_img.shape, img.shape, ref_img.path, img.path)
        acc.add(img, ts[i])
    rad, valid, n_inv, n_fb, used = acc.result()
    return MergeResult(rad, valid, n_inv, n_fb, used, tuple(ts[i] for i in order), tuple(paths[i] for i in order),
                       units, t_ref, np.asarray(ref_img.wb, np.float32))


def apply_response(img8: np.ndarray, response: np.ndarray) -> np.ndarray:
    """Linearise an 8-bit RGB image with a (256, 3) response (value -> relative exposure), float32 (H, W, 3)."""
    resp = np.asarray(response, np.float32).reshape(256, 3)
    return np.stack([resp[img8[..., c], c] for c in range(3)], axis=-1)


def merge_ldr_bracket(paths: Sequence[str | Path], times: Sequence[float | None] | None = None, *,
                      samples: int = 70, smoothness: float = 10.0, sat_level: int = 250,
                      units: str = "reference") -> tuple[MergeResult, np.ndarray]:
    """Merge a bracket of JPEG/PNG views with a Debevec response recovered from the bracket itself.

    Returns (result, response) with ``response`` (256, 3) float32 in RGB order: OpenCV's recovered curve
    (relative exposure per pixel value, 1 at 128), made non-decreasing. Pixels with a channel at or above
    ``sat_level`` in every frame are flagged invalid. Units: see the module doc (relative radiance).
    """
    import cv2

    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise InputError("a JPEG/PNG bracket needs at least two exposures to recover the response curve",
                         paths[0] if paths else None, "give an exposure bracket, or raws")
    if units not in UNITS:
        raise ValueError(f"units must be one of {UNITS}")
    ts = _resolve_times(paths, times)
    _check_times(ts, paths)
    _check_same([read_exif(p) for p in paths], paths)
    order = sorted(range(len(paths)), key=lambda i: ts[i])
    imgs = [read_ldr(paths[i]) for i in order]
    for k in range(1, len(imgs)):
        _check_shapes(imgs[0].shape[:2], imgs[k].shape[:2], paths[order[0]], paths[order[k]])
    tsort = np.array([ts[i] for i in order], np.float32)
    bgr = [np.ascontiguousarray(im[..., ::-1]) for im in imgs]
    response = cv2.createCalibrateDebevec(samples, smoothness, False).process(bgr, tsort)
    hdr = cv2.createMergeDebevec().process(bgr, tsort, response)
    resp = np.maximum.accumulate(response.reshape(256, 3)[:, ::-1].astype(np.float32), axis=0)
    all_sat = np.ones(imgs[0].shape[:2], bool)
    for im in imgs:
        all_sat &= np.any(im >= sat_level, axis=2)
    t_ref = float(tsort[-1]) if units == "reference" else 1.0
    rad = np.ascontiguousarray(hdr[..., ::-1], dtype=np.float32) * np.float32(t_ref)
    shortest = apply_response(imgs[0], resp) * np.float32(t_ref / tsort[0])
    rad[all_sat] = shortest[all_sat]  # OpenCV's weights never reach zero; keep the documented fill rule
    used = np.zeros(all_sat.shape, np.uint8)
    for im in imgs:
        used += np.all((im > 5) & (im < sat_level), axis=2)
    res = MergeResult(rad, ~all_sat, int(all_sat.sum()), 0, used, tuple(float(t) for t in tsort),
                      tuple(paths[i] for i in order), units, t_ref, np.ones(3, np.float32))
    return res, resp
