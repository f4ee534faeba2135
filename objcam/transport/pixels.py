"""Pixel pooling and sub-pixel sample positions shared by the transport and solve stages.

A pooled pixel (row R, column C) of factor f is the mean of the original f x f block of pixels with rows
f R .. f R + f - 1 and columns f C .. f C + f - 1; its footprint in continuous pixel coordinates (OpenCV pixel
centres at integers) is [f C - 1/2, f C + f - 1/2] x [f R - 1/2, f R + f - 1/2]. Trailing rows and columns
that do not fill a whole block are dropped, so the pooled image has shape (H // f, W // f).
"""

from __future__ import annotations

import numpy as np


def pooled_shape(height: int, width: int, f: int) -> tuple[int, int]:
    """Shape of the pooled image (H // f, W // f)."""
    if f < 1:
        raise ValueError("downsample factor must be >= 1")
    return height // f, width // f


def pool_target(image: np.ndarray, valid: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
    """Pool a target the way the transport stage pools A.

    image (H, W, 3) -> (H // f, W // f, 3) block means; valid (H, W) bool -> (H // f, W // f) bool, True only
    where every pixel of the block is valid. Invalid pixels may hold anything (NaN included): a block with one is
    invalid, and its pooled value is set to 0.
    """
    f = int(f)
    img = np.asarray(image)
    ok = np.asarray(valid, dtype=bool)
    if img.shape[:2] != ok.shape:
        raise ValueError(f"image {img.shape[:2]} and valid mask {ok.shape} differ in shape")
    hp, wp = pooled_shape(ok.shape[0], ok.shape[1], f)
    if f == 1:
        out = np.where(ok[..., None], img, 0).astype(np.float32)
        return out, ok.copy()
    img = img[: hp * f, : wp * f]
    ok = ok[: hp * f, : wp * f]
    vblock = ok.reshape(hp, f, wp, f).all(axis=(1, 3))
    safe = np.where(ok[..., None], img, 0).astype(np.float64)
    mean = safe.reshape(hp, f, wp, f, -1).mean(axis=(1, 3))
    mean[~vblock] = 0.0
    return mean.astype(np.float32), vblock


def target_rows(image: np.ndarray, valid: np.ndarray, f: int,
                pixel_index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A target photo at A's rows: (pooled (H', W', 3), pooled_ok (H', W') bool, y (M, 3) float64, use (M,) bool),
    the pooled image and its usable pixels (:func:`pool_target`) and both at the kept pixels ``pixel_index``."""
    pooled, ok = pool_target(image, valid, f)
    y = pooled.reshape(-1, 3)[pixel_index].astype(np.float64)
    return pooled, ok, y, ok.reshape(-1)[pixel_index]


def pool_mask_any(mask: np.ndarray, f: int) -> np.ndarray:
    """(H // f, W // f) True where any pixel of the block is set."""
    hp, wp = pooled_shape(mask.shape[0], mask.shape[1], f)
    return np.asarray(mask, bool)[: hp * f, : wp * f].reshape(hp, f, wp, f).any(axis=(1, 3))


# Joe & Kuo (2008) primitive polynomials (degree s, coefficients a) and initial direction numbers m of Sobol
# dimensions 2-4; dimension 1 is the van der Corput sequence.
_SOBOL = ((1, 0, (1,)), (2, 1, (1, 3)), (3, 1, (1, 3, 1)))


def _direction_numbers(s: int, a: int, m: tuple[int, ...]) -> list[int]:
    v = [m[j] << (31 - j) for j in range(s)]
    for j in range(s, 32):
        x = v[j - s] ^ (v[j - s] >> s)
        for k in range(1, s):
            if (a >> (s - 1 - k)) & 1:
                x ^= v[j - k]
        v.append(x)
    return v


def sobol4(n: int) -> np.ndarray:
    """The first n points of the 4D Sobol sequence (natural order, unscrambled) as 32-bit integers (n, 4).

    Every aligned block of 2^m consecutive points is a (t, m, 4)-net (dimensions 0-1 alone: a (0, m, 2)-net);
    a random digital shift (XOR) keeps that. Dimensions 0-1 place sub-pixel samples, 2-3 the shadow-ray
    direction paired with each.
    """
    i = np.arange(n, dtype=np.uint64)
    out = np.zeros((n, 4), np.uint64)
    dirs = [[1 << (31 - j) for j in range(32)]] + [_direction_numbers(*p) for p in _SOBOL]
    for bit in range(32):
        on = ((i >> np.uint64(bit)) & np.uint64(1)).astype(bool)
        if not on.any():
            break
        for d in range(4):
            out[on, d] ^= np.uint64(dirs[d][bit])
    return out.astype(np.uint32)


def to_unit(x: np.ndarray) -> np.ndarray:
    """32-bit integers -> [0, 1) (24-bit resolution, centred in their cell)."""
    return ((np.asarray(x, dtype=np.uint32) >> np.uint32(8)).astype(np.float64) + 0.5) / float(1 << 24)


def subpixel_positions(pixel_index: np.ndarray, pooled_width: int, f: int, n: int,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Continuous original-image coordinates (u, v), each (M, n), of n stratified samples over the f x f
    footprint of each pooled pixel ``pixel_index`` (flat row * pooled_width + col).

    The samples are the first n Sobol points (dimensions 0-1 of :func:`sobol4`) with a random digital shift per
    pixel: any aligned block of 2^m of them is stratified on its own (the direct model traces shadow rays from
    such blocks).
    """
    pix = np.asarray(pixel_index, dtype=np.int64)
    row, col = pix // pooled_width, pix % pooled_width
    pts = sobol4(n)
    x, y = pts[:, 0], pts[:, 1]
    sh = rng.integers(0, 1 << 32, size=(pix.size, 2), dtype=np.uint64).astype(np.uint32)
    su = to_unit(x[None, :] ^ sh[:, :1])
    sv = to_unit(y[None, :] ^ sh[:, 1:])
    u = f * col[:, None] - 0.5 + f * su
    v = f * row[:, None] - 0.5 + f * sv
    return u, v
