"""The target photos registered to the model at sub-pixel precision (``solve.align``).

The solve fits shadow edges pixel by pixel, so a camera pose a fraction of a pixel off is paid for by the envmap.
Measured on the demo capture (128 x 128, known camera moved on purpose): turned 0.08 deg (the image 0.25 px off)
SSIM 0.607 -> 0.249; moved 0.5 mm (0.27 px) 0.509; 1.2 mm (0.64 px) 0.313. SfM poses targets to about that (the
photographed sweep: 0.2-2 mm, 0.03-0.3 deg), and a camera file measured by hand is no better.

After a solve, the image shift d (pixels of A's grid) that maps the model's prediction onto the photos,
Y(p) = P(p + d), is found by Gauss-Newton on the prediction's luminance gradient over the usable pixels of every
target of one camera (one pose: one shift), with Huber weights against the residuals' robust spread. When it is
significant (over 3 of its standard errors and over :data:`MIN_SHIFT_PX`), every photo of that camera is resampled
by it at full resolution (bilinear; a pixel whose resampling touches an unusable one becomes unusable), pooled to
A's grid again and the capture solved again; up to :data:`ROUNDS` rounds, the shifts adding up. A round is kept
only when that solve removes at least :data:`MIN_GAIN` of the misfit beyond the noise (:func:`fit_gain`): model
error leans on the gradients too, and its "shift" buys little. A shift is exact for a camera turned about its
centre by a small angle and close to it for a small move (the demo moved 1.2 mm: 0.313 -> 0.531, against 0.607
with the true camera: the move's parallax across the object's depth is not a shift).
"""

from __future__ import annotations

import numpy as np

#: Rounds of (estimate the shift, resample, solve again) at most.
ROUNDS = 3
#: Shifts under this many pixels of A's grid are left alone (a twentieth of a pixel: on the demo 0.25 px cost 0.36
#: SSIM, so a twentieth costs about 0.02 at most).
MIN_SHIFT_PX = 0.05
#: Huber weights beyond this many robust spreads of the residual.
HUBER_K = 3.0
#: A shift larger than this (pixels of A's grid) is not a pose error the linearised step can follow: stop.
MAX_SHIFT_PX = 3.0
#: A round is kept only when the solve after it misfits less by at least this share of the misfit beyond the noise
#: before it (chi2 - 1, at least a tenth of chi2). A pose error is most of that excess (the demo turned 0.08 deg:
#: chi2 1.49 -> 0.83; moved 0.5 mm 1.27 -> 0.83), while model error also leans on the prediction's gradients and
#: yields a small "shift" that buys little (a 48 x 48 direct-light capture at 8 rows, chi2 36.8 -> 36.2, SSIM
#: 0.893 -> 0.882, an albedo worse: not kept).
MIN_GAIN = 0.2


def _luma(img: np.ndarray) -> np.ndarray:
    return np.asarray(img, np.float64)[..., :3].mean(axis=-1)


def estimate_shift(preds: list[np.ndarray], photos: list[np.ndarray], usable: list[np.ndarray]) -> dict:
    """The shift d = (dx, dy) in pixels of A's grid with photo(p) = prediction(p + d), one for all the pairs.

    preds, photos: (H', W', 3) the model's image and the pooled photo of each target of one camera; usable:
    (H', W') bool, pixels fitted (the photo usable, a row of A, not an outlier). Returns {"shift": (2,), "stderr":
    (2,), "pixels": n}; the shift is NaN when fewer than 10 pixels have a gradient.
    """
    rows_j, rows_r = [], []
    for p, y, ok in zip(preds, photos, usable):
        lp, ly = _luma(p), _luma(y)
        inner = ok.copy()
        inner[:, 0] = inner[:, -1] = inner[0, :] = inner[-1, :] = False
        inner[:, 1:-1] &= ok[:, :-2] & ok[:, 2:]
        inner[1:-1, :] &= ok[:-2, :] & ok[2:, :]
        gx = np.zeros_like(lp)
        gy = np.zeros_like(lp)
        gx[:, 1:-1] = 0.5 * (lp[:, 2:] - lp[:, :-2])
        gy[1:-1, :] = 0.5 * (lp[2:, :] - lp[:-2, :])
        rows_j.append(np.stack([gx[inner], gy[inner]], axis=1))
        rows_r.append((ly - lp)[inner])
    J, r = np.concatenate(rows_j), np.concatenate(rows_r)
    strong = np.abs(J).sum(axis=1) > 0
    if strong.sum() < 10:
        return {"shift": np.full(2, np.nan), "stderr": np.full(2, np.nan), "pixels": int(strong.sum())}
    J, r = J[strong], r[strong]
    d = np.zeros(2)
    for _ in range(5):  # iteratively reweighted: the weights follow the residual after the shift
        e = r - J @ d
        scale = 1.4826 * np.median(np.abs(e - np.median(e))) + 1e-30
        w = np.minimum(1.0, HUBER_K * scale / np.maximum(np.abs(e), 1e-30))
        H = (J * w[:, None]).T @ J
        d = np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(2), (J * w[:, None]).T @ r)
    e = r - J @ d
    scale = 1.4826 * np.median(np.abs(e - np.median(e)))
    cov = np.linalg.inv(H + 1e-12 * np.trace(H) * np.eye(2)) * scale ** 2
    return {"shift": d, "stderr": np.sqrt(np.clip(np.diag(cov), 0, None)), "pixels": int(r.size)}


def significant(est: dict, min_px: float = MIN_SHIFT_PX) -> bool:
    """Whether an :func:`estimate_shift` result is worth resampling for: finite, over ``min_px`` and over 3 of its
    standard errors, and under :data:`MAX_SHIFT_PX`."""
    d, s = est["shift"], est["stderr"]
    if not np.all(np.isfinite(d)):
        return False
    n = float(np.hypot(*d))
    return min_px < n < MAX_SHIFT_PX and n > 3.0 * float(np.hypot(*s))


def fit_gain(before: list[float], after: list[float]) -> float:
    """The share of the misfit beyond the noise that a round removed: (sum(before) - sum(after)) over
    max(sum(before) - n, sum(before) / 10), from the chi-squared per value of the n targets it moved."""
    b, a = float(np.sum(before)), float(np.sum(after))
    return (b - a) / max(b - len(before), 0.1 * b, 1e-30)


def shift_image(image: np.ndarray, valid: np.ndarray, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The photo (H, W, C) and its usable mask (H, W) resampled so that out(u) = image(u - shift), shift (2,) =
    (dx, dy) in the photo's pixels: bilinear, a pixel whose four sources include an unusable one (or lie outside)
    unusable, and 0 there."""
    import cv2

    h, w = valid.shape
    m = np.array([[1.0, 0.0, -float(shift[0])], [0.0, 1.0, -float(shift[1])]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    img = np.asarray(image, np.float32)
    out = np.stack([cv2.warpAffine(np.ascontiguousarray(img[..., c]), m, (w, h), flags=flags,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
                    for c in range(img.shape[2])], axis=-1)
    bad = cv2.warpAffine((~np.asarray(valid, bool)).astype(np.float32), m, (w, h), flags=flags,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
    ok = bad <= 0.0
    out[~ok] = 0.0
    return out, ok
