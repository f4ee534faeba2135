"""Image and file I/O: linear EXR through OpenImageIO, tonemapped PNGs, and atomic writes.

Every file objcam writes goes through a temporary name in the same folder and an ``os.replace``, so a killed
process leaves either the old file or the new one, never half of one.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from objcam.errors import InputError


def _umask() -> int:
    old = os.umask(0)
    os.umask(old)
    return old


_FILE_MODE = 0o666 & ~_umask()


def _tmp_path(path: Path) -> Path:
    """A temporary file beside ``path`` with ordinary permissions (mkstemp alone would leave 0600)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.fchmod(fd, _FILE_MODE)
    os.close(fd)
    return Path(tmp)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path)
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def read_exr(path: str | Path) -> np.ndarray:
    """Read an image with OpenImageIO as float32 (H, W, C). Raises InputError naming the file."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise InputError("image not found", path, "check the path in capture.toml")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"cannot read image ({oiio.geterror().strip() or 'unknown format'})", path,
                         "give a linear HDR image (EXR, or PFM/HDR)")
    try:
        spec = inp.spec()
        arr = inp.read_image(0, 0, 0, spec.nchannels, "float")
    finally:
        inp.close()
    if arr is None or arr.size == 0:
        raise InputError("image has no pixels or is truncated", path, "re-export the image")
    arr = np.asarray(arr, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    return arr


def write_exr(path: str | Path, image: np.ndarray, half: bool = False) -> None:
    """Write (H, W[, C]) linear values to an EXR atomically (float32 unless ``half``)."""
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    h, w, c = img.shape
    tmp = _tmp_path(path)
    try:
        spec = oiio.ImageSpec(w, h, c, "half" if half else "float")
        if c == 3:
            spec.channelnames = ("R", "G", "B")
        elif c == 1:
            spec.channelnames = ("Y",)
        spec.attribute("compression", "zip")
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(img))
        out.close()
        if not ok:
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def tonemap(image: np.ndarray, exposure_ref: float | None = None, gamma: float = 2.2,
            percentile: float = 99.0) -> tuple[np.ndarray, float]:
    """Linear HDR -> display values in [0, 1]: divide by a reference (default the ``percentile`` of the finite
    values), clip to 1, gamma 1/``gamma``. Returns (display image, reference used) so a second image can share
    the same exposure.
    """
    img = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if exposure_ref is None:
        pos = img[img > 0]
        exposure_ref = float(np.percentile(pos, percentile)) if pos.size else 1.0
    exposure_ref = exposure_ref if exposure_ref > 0 else 1.0
    return np.clip(img / exposure_ref, 0.0, 1.0) ** (1.0 / gamma), exposure_ref


def write_png(path: str | Path, display: np.ndarray) -> None:
    """Write display values in [0, 1] (H, W[, 3]) as an 8-bit PNG, atomically."""
    import cv2

    path = Path(path)
    img = np.clip(np.asarray(display, dtype=np.float64), 0, 1)
    img8 = (img * 255.0 + 0.5).astype(np.uint8)
    if img8.ndim == 3 and img8.shape[2] == 3:
        img8 = img8[..., ::-1]  # RGB -> BGR for OpenCV
    ok, buf = cv2.imencode(".png", img8)
    if not ok:
        raise OSError(f"cannot encode {path}")
    atomic_write_bytes(path, buf.tobytes())


def write_tonemapped_png(path: str | Path, image: np.ndarray, exposure_ref: float | None = None,
                         gamma: float = 2.2) -> float:
    """Tonemap (see :func:`tonemap`) and write a PNG; returns the exposure reference used."""
    display, ref = tonemap(image, exposure_ref, gamma)
    write_png(path, display)
    return ref


def save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """Atomically write a compressed .npz."""
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())
