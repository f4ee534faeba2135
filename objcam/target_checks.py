"""Checks of one target image before it is fitted: its encoding (a linear float image, or an integer image the
capture says how to linearise), its negative values against its own noise (zero-mean noise is data; negatives
far beyond it are not), isolated hot pixels, and whether its camera sees the object and the ground around it.
Each failure is an InputError naming the file and the fix (data_layout.md, "Checks")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from objcam.errors import InputError

# Negatives: a pixel below -NEG_SIGMAS sigma, or more than NEG_AREA of the pixels below -3 sigma (Gaussian noise
# puts 0.13% there), is not noise: a wrong black level, a signed difference image, a broken export.
NEG_SIGMAS = 6.0
NEG_AREA = 0.01
# Hot pixels: brighter than HOT_FACTOR x the brightest of its 8 neighbours and x the image's 99th percentile.
# A diffuse scene is smooth at the pixel scale (an edge pixel has a bright neighbour on its lit side).
HOT_FACTOR = 20.0
HOT_MAX_FRACTION = 1e-3  # more than this many isolated spikes: refuse rather than mask


def _srgb_to_linear(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_target(path: Path, encoding: str | None) -> np.ndarray:
    """The image as linear float32 (H, W, C). Integer images (8/16-bit PNG, JPEG, TIFF) need ``encoding``:
    'srgb' applies the sRGB curve, 'linear' takes code values / max code as linear."""
    import OpenImageIO as oiio

    from objcam.image_io import read_exr

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()  # read_exr below reports it, naming the file; a pending error would print at exit
        fmt = ""
    else:
        fmt = str(inp.spec().format)
        inp.close()
    img = read_exr(path)
    if fmt not in ("float", "half", "double"):
        if encoding is None:
            raise InputError(f"image is {fmt or 'integer'} (8/16-bit display values, e.g. sRGB), not linear HDR "
                             "radiance", path, "give a float EXR, or set encoding = \"srgb\" or \"linear\" for this "
                             "target in capture.toml")
        if encoding == "srgb":
            img = _srgb_to_linear(np.clip(img, 0.0, 1.0))
    return img


def noise_level(rgb: np.ndarray, valid: np.ndarray, noise_sigma: float | None) -> tuple[np.ndarray | None, str]:
    """Absolute noise sigma per channel (3,): ``noise_sigma`` x the median positive value when the capture gives
    it, else Immerkaer's Laplacian estimate over the valid pixels; None when neither is possible."""
    from objcam.transport.auto import MEAN_LAPLACIAN_TO_SIGMA, laplacian_channels

    if noise_sigma:
        pos = rgb[valid][rgb[valid] > 0]
        return np.full(3, noise_sigma * (float(np.median(pos)) if pos.size else 1.0)), "noise_sigma"
    parts = laplacian_channels(rgb[..., :3], valid)
    if parts is None:
        return None, "unknown"
    return np.array([MEAN_LAPLACIAN_TO_SIGMA * float(np.mean(lap)) for _, lap in parts]), "estimated"


def check_negatives(rgb: np.ndarray, valid: np.ndarray, noise_sigma: float | None, path: Path) -> dict:
    """Refuse negatives beyond the noise (rule above); return what was found for the stage's metrics."""
    neg = rgb[valid]
    lo = float(neg.min()) if neg.size else 0.0
    if lo >= 0:
        return {"negative_pixels": 0}
    sigma, source = noise_level(rgb, valid, noise_sigma)
    scale = float(np.abs(rgb[valid]).max()) if neg.size else 1.0
    if sigma is None or not np.all(sigma > 0):
        if lo < -1e-6 * max(scale, 1e-30):
            raise InputError(f"image has negative values (min {lo:.3g}) and its noise level is unknown", path,
                             "give noise_sigma for this target in capture.toml, or a linear image with values >= 0")
        return {"negative_pixels": int((neg < 0).sum())}
    z = rgb[valid] / sigma  # per channel, in units of the noise
    worst = float(z.min())
    far = float((z < -3.0).mean())
    if worst < -NEG_SIGMAS:
        raise InputError(f"image has negative values far beyond its noise (min {lo:.3g} = {-worst:.1f} sigma, "
                         f"sigma {float(sigma.mean()):.3g} from {source}; refused below -{NEG_SIGMAS:g} sigma)", path,
                         "subtract the right black level (zero-mean noise is fine), or give the true noise_sigma")
    if far > NEG_AREA:
        raise InputError(f"image has a large negative area ({far:.1%} of pixels below -3 sigma, noise allows "
                         f"{NEG_AREA:.0%})", path, "subtract the right black level (zero-mean noise is fine)")
    return {"negative_pixels": int((rgb[valid] < 0).any(axis=1).sum()), "negative_min_sigma": round(worst, 2)}


def hot_pixels(rgb: np.ndarray, valid: np.ndarray, path: Path) -> np.ndarray:
    """Mask (H, W) of isolated spikes (rule above), to be excluded from the fit; refuses an image with many."""
    from scipy.ndimage import maximum_filter

    lum = rgb.max(axis=2).astype(np.float64)
    foot = np.ones((3, 3), bool)
    foot[1, 1] = False
    neigh = maximum_filter(lum, footprint=foot, mode="nearest")
    ref = float(np.percentile(lum[valid], 99.0)) if valid.any() else 0.0
    hot = valid & (lum > HOT_FACTOR * np.maximum(neigh, 0)) & (lum > HOT_FACTOR * max(ref, 0)) & (lum > 0)
    if hot.sum() > max(1, HOT_MAX_FRACTION * valid.sum()):
        raise InputError(f"image has {int(hot.sum())} isolated hot pixels (over {HOT_FACTOR:g}x their neighbours "
                         "and the image's 99th percentile)", path, "fix the image, or mask those pixels")
    return hot


def check_in_view(cam, vertices: np.ndarray, cam_path: Path) -> None:
    """Refuse a camera that sees neither the object nor the ground around it (where its shadow falls)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    size = float(np.max(hi - lo))
    centre = (lo + hi) / 2
    ring = [centre + size * np.array([np.cos(a), np.sin(a), 0.0]) for a in np.linspace(0, 2 * np.pi, 16, False)]
    ground = np.array(ring) * np.array([1, 1, 0])

    def seen(points: np.ndarray) -> bool:
        inv = np.linalg.inv(cam.matrix)
        p = points @ inv[:3, :3].T + inv[:3, 3]
        front = p[:, 2] > 1e-9
        if not front.any():
            return False
        uv = cam.project(points[front])
        return bool(((uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5) & (uv[:, 1] >= -0.5)
                     & (uv[:, 1] <= cam.height - 0.5)).any())

    if not seen(vertices[:: max(1, len(vertices) // 5000)]):
        raise InputError("the camera does not see the object (no vertex projects into the image)", cam_path,
                         "check world_from_camera (camera-to-world, OpenCV axes, metres) and the intrinsics")
    if not seen(ground):
        raise InputError("the camera does not see the ground around the object, where its shadows fall", cam_path,
                         "frame the object and its shadow (check world_from_camera and the intrinsics)")
