"""Is the chrome ball's bracket exposed right? Checks on a merged bracket, each naming the frame to change.

A merged bracket here is a :class:`~objcam.capture.hdr.MergeResult` or a :class:`~objcam.probe.merged.MergedProbe`
(ingest's ``image.exr`` with ``valid.png`` and ``merge.json``): ``radiance`` (H, W, 3), ``valid`` (H, W) bool (False:
saturated in every frame), ``times`` (ascending, seconds), ``paths`` (same order), ``units`` ("reference": the
longest frame's units; "per_second") and ``wb`` (white-balance multipliers in the data).

What each frame recorded is recovered from the merge: the brightest channel before white balance, in
white-level units, is ``max_c(radiance / wb)`` times ``t_k / t_longest`` ("reference") or times ``t_k``
("per_second"); the merge used a frame where that lies in (``LOW``, ``HIGH``) (objcam.capture.hdr's defaults).

- saturated everywhere: more than half of the image, or of the ball, saturated in every frame -> an InputError
  naming the SHORTEST frame: add shorter exposures;
- exposed nowhere: more than half of it below ``LOW`` in every frame (no usable signal) -> an InputError naming
  the LONGEST frame: add longer exposures (over the whole image from the merge's ``n_fallback`` count when it
  has no per-pixel ``frames_used``, as ingest's merge.json: the merged value of such a pixel is the least exposed
  frame's noise scaled up, no level);
- saturates nowhere (a warning, not an error: the probe is still measured, only noisier): the longest frame
  clips nowhere on the ball and the ball's median pixel sits below ``DIM_MEDIAN`` of the white level in it,
  so the bracket stops short of the dark end and the dim reflections are noisy -> names the LONGEST frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from objcam.errors import InputError

LOW, HIGH = 0.002, 0.9  # a frame's usable range (white-level units), as objcam.capture.hdr.merge_frames
MAX_BAD_FRACTION = 0.5  # more of the region than this saturated (or dark) in every frame: an error
DIM_MEDIAN = 1.0 / 32.0  # longest frame's median ball level below this (and no clipping there): a warning
SHOOT_SHORTER = ("add shorter exposures (2-3 stops apart) until the brightest part of the ball, the sun aside, is "
                 "below the white level in the shortest frame")
SHOOT_LONGER = ("add longer exposures (2-3 stops apart) until the ball's darkest reflections reach about 1/4 of "
                "the white level in the longest frame")


def longest_level(merge) -> np.ndarray | None:
    """(H, W) float32: the brightest channel (before white balance) each pixel recorded in the longest frame,
    in white-level units (> 1 where that frame clipped: the merge's estimate), or None when the merge's units
    do not allow it (relative radiance from a JPEG bracket, or no exposure times)."""
    times = tuple(getattr(merge, "times", ()) or ())
    units = getattr(merge, "units", None)
    if not times or units not in ("reference", "per_second"):
        return None
    wb = np.asarray(getattr(merge, "wb", None) if getattr(merge, "wb", None) is not None else np.ones(3),
                    np.float32).reshape(-1)[:3]
    level = np.max(np.asarray(merge.radiance, np.float32)[..., :3] / wb, axis=2)
    return level * np.float32(times[-1]) if units == "per_second" else level


def frames_used(merge) -> np.ndarray | None:
    """(H, W) uint8: frames whose recorded value lay in (LOW, HIGH) per pixel (the merge's own count when it has
    one, else recovered from :func:`longest_level`); 0 where saturated in every frame. None when unknown."""
    used = getattr(merge, "frames_used", None)
    if used is not None:
        return np.asarray(used)
    level = longest_level(merge)
    if level is None:
        return None
    times = np.asarray(merge.times, np.float64)
    count = np.zeros(level.shape, np.uint8)
    for t in times:
        lk = level * np.float32(t / times[-1])
        count += ((lk > LOW) & (lk < HIGH)).astype(np.uint8)
    count[~np.asarray(merge.valid, bool)] = 0
    return count


def _frame(merge, shortest: bool) -> Path | None:
    paths = getattr(merge, "paths", ())
    if not paths:
        return None
    return Path(paths[0] if shortest else paths[-1])


def _time(merge, shortest: bool) -> str:
    times = getattr(merge, "times", ())
    return f" ({times[0 if shortest else -1]:.4g} s)" if times else ""


def check_bracket(merge, region: np.ndarray | None = None, what: str = "the image") -> None:
    """Raise InputError when ``region`` (bool (H, W), default everything) of a merged bracket is mostly saturated
    in every frame, or mostly without a usable frame (see the module doc)."""
    valid = np.asarray(merge.valid, bool)
    m = np.ones(valid.shape, bool) if region is None else np.asarray(region, bool)
    n = int(m.sum())
    if n == 0:
        return
    sat = float((~valid & m).sum()) / n
    if sat > MAX_BAD_FRACTION:
        raise InputError(f"{100 * sat:.0f}% of {what} is saturated in every frame of the bracket, even the "
                         f"shortest{_time(merge, True)}", _frame(merge, True), SHOOT_SHORTER)
    n_fallback = getattr(merge, "n_fallback", None)
    used = getattr(merge, "frames_used", None)
    if region is None and used is None and n_fallback is not None:
        # the whole image, from ingest's record: a pixel with no usable frame holds the merge's fallback, whose
        # level (the least exposed frame's noise scaled up) is no measure of what the frames recorded
        dark = float(n_fallback) / n
    else:
        used = frames_used(merge)
        if used is None:
            return
        dark = float((valid & (used == 0) & m).sum()) / n
    if dark > MAX_BAD_FRACTION:
        raise InputError(f"{100 * dark:.0f}% of {what} has no usable signal in any frame of the bracket, even "
                         f"the longest{_time(merge, False)}", _frame(merge, False), SHOOT_LONGER)


def dim_warning(merge, region: np.ndarray) -> str | None:
    """A warning when the longest frame clips nowhere in ``region`` (the ball's pixels) and the region's median
    there is below ``DIM_MEDIAN`` of the white level (see the module doc), else None."""
    level = longest_level(merge)
    m = np.asarray(region, bool) & np.asarray(merge.valid, bool)
    if level is None or not m.any():
        return None
    lv = level[m]
    med = float(np.median(lv))
    if float(lv.max()) >= HIGH or med >= DIM_MEDIAN:
        return None
    frame = _frame(merge, False)
    name = frame.name if frame is not None else "the longest frame"
    return (f"{name}{_time(merge, False)}, the bracket's longest frame, saturates nowhere on the chrome ball and "
            f"its median ball pixel is at {100 * med:.1f}% of the white level: the dim reflections are noisy; "
            + SHOOT_LONGER)
