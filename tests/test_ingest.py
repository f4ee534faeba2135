"""Capture front end: synthetic DNGs read back exactly, bracket merges recover radiance, bad input is one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from objcam.capture.dng import NoiseModel, synth_bracket, write_dng
from objcam.capture.exif import MISSING_EXPOSURE_FIX, exposure_time, read_exif
from objcam.capture.hdr import merge_ldr_bracket, merge_raw_bracket
from objcam.capture.raw import read_ldr, read_raw, read_tiff16
from objcam.errors import InputError

BLACK, WHITE = 512, 16383
TIMES = [2.0 ** -12 * 4 ** k for k in range(5)]  # 1/4096 .. 1/16 s, 2 stops apart


def block2(img: np.ndarray) -> np.ndarray:
    """Half-resolution image -> 2x2-block-constant full resolution (so superpixel truth is exact)."""
    return img.repeat(2, 0).repeat(2, 1)


def ramp_signal(h=48, w=64) -> np.ndarray:
    """Half-res linear signal in white-level units: per-channel ramps 0.02..0.95, plus a saturated corner."""
    yy, xx = np.mgrid[0:h, 0:w]
    sig = np.stack([0.02 + 0.93 * xx / (w - 1), 0.02 + 0.93 * yy / (h - 1), np.full((h, w), 0.42)], -1)
    sig[:3, :3] = 1.5
    return sig


def assert_one_line_naming(err: pytest.ExceptionInfo, path: Path, *words: str) -> None:
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and "fix:" in msg, msg
    for w in words:
        assert w.lower() in msg.lower(), msg


# -- DNG round trip ---------------------------------------------------------------------------------------------

def test_dng_round_trip_levels_and_metadata(tmp_path):
    import exifread
    import rawpy

    half = ramp_signal()
    t = 1 / 320
    p = write_dng(tmp_path / "a.dng", block2(half), exposure_time=t, iso=400, f_number=5.6, make="Objcam",
                  model="Synth 1", black_level=BLACK, white_level=WHITE, wb=(2.0, 1.0, 1.5))
    with rawpy.imread(str(p)) as r:
        assert list(r.black_level_per_channel) == [BLACK] * 4 and r.white_level == WHITE
        assert r.raw_image_visible.max() == WHITE  # clipped at the white level, exactly
        np.testing.assert_allclose(r.camera_whitebalance[:3], [2.0, 1.0, 1.5], rtol=1e-4)
    with open(p, "rb") as f:
        tags = exifread.process_file(f, details=False)
    assert float(tags["EXIF ExposureTime"].values[0]) == pytest.approx(t, rel=1e-9)
    info = read_exif(p)
    assert (info.exposure_time, info.iso, info.f_number, info.make, info.model) == \
        (pytest.approx(t), 400, pytest.approx(5.6), "Objcam", "Synth 1")

    img = read_raw(p)  # superpixel, no white balance
    sat = img.saturated
    assert sat[:3, :3].all() and sat.sum() == 9
    assert np.all(img.rgb[sat] == 1.0)  # white level maps to exactly 1.0
    # exact up to rounding to integer DN: at most half a DN of the 15871-DN range
    assert np.abs(img.rgb[~sat] - half[~sat]).max() <= 0.5 / (WHITE - BLACK) * 1.001
    assert np.median(np.abs(img.rgb[~sat] / half[~sat] - 1)) < 1e-4
    # the file's as-shot white balance
    wb = read_raw(p, wb="camera")
    np.testing.assert_allclose(wb.rgb[~sat], img.rgb[~sat] * [2.0, 1.0, 1.5], rtol=1e-5)
    # flat field: LibRaw's pipeline with the linear settings, and bilinear, are exact too (no 3% / 40% drift)
    flat = write_dng(tmp_path / "flat.dng", np.broadcast_to([0.25, 0.5, 0.75], (64, 96, 3)), exposure_time=t,
                     black_level=2048, white_level=WHITE)
    for method in ("postprocess", "bilinear"):
        other = read_raw(flat, demosaic=method)
        assert other.rgb.shape == (64, 96, 3) and not other.saturated.any()
        np.testing.assert_allclose(np.median(other.rgb, axis=(0, 1)), [0.25, 0.5, 0.75], rtol=2e-4)


NOISE_WELL = 40000.0  # electrons at ISO 100


def noise_missed(rgb: np.ndarray) -> list[str]:
    """The bounds that the decoded superpixel image ``rgb`` (H, W, 3, white-level units) of a flat 0.3 field, shot
    at ISO 100 with a 40,000 e- full well, misses: "mean" (within 0.2% of 0.3) and "std" (red, one CFA sample per
    pixel: shot noise sqrt(0.3 * 40000) e-, within 10%). Measured: mean -0.006%, red std +0.16%; a 1024-sample std
    scatters 2.2% (1 / sqrt(2 n)), so 10% is 4.5 of its sigma (was 15%, which nothing below needed)."""
    missed = []
    if not abs(rgb.mean() / 0.3 - 1) < 2e-3:
        missed.append("mean")
    if not rgb[..., 0].std() == pytest.approx(np.sqrt(0.3 * NOISE_WELL) / NOISE_WELL, rel=0.10):
        missed.append("std")
    return missed


def noisy_flat(path: Path, **kw) -> np.ndarray:
    """The decoded (superpixel) image of a flat 0.3 field written as a noisy DNG with ``kw`` for write_dng."""
    kw = {"iso": 100, "noise": NoiseModel(full_well_e=NOISE_WELL), **kw}
    return read_raw(write_dng(path, block2(np.full((32, 32, 3), 0.3)), exposure_time=0.01, **kw)).rgb


def test_noisy_dng_and_tiff16(tmp_path):
    """A noisy DNG keeps its mean and its shot noise (broken variants: NOISE_BROKEN below); 16-bit TIFF levels
    read back exactly."""
    # 2 greens binned: shot noise sqrt(0.3 * 40000) e- per sample
    assert noise_missed(noisy_flat(tmp_path / "n.dng")) == []

    import cv2

    t16 = np.zeros((8, 10, 3), np.uint16)
    t16[..., 0], t16[..., 1], t16[..., 2], t16[0, 0] = 1000, 30000, 65000, 65535
    cv2.imwrite(str(tmp_path / "lin.tif"), t16[..., ::-1])
    lin = read_tiff16(tmp_path / "lin.tif")
    np.testing.assert_allclose(lin.rgb[1, 1], [1000 / 65535, 30000 / 65535, 65000 / 65535], rtol=1e-6)
    assert lin.saturated[0, 0] and lin.saturated.sum() == 80  # 65000 >= 99% of 65535 too


# deliberately broken noise (tests/broken.py), each must miss the bounds above (measured in the comments)
NOISE_BROKEN = {
    # the gain misread: shot at ISO 400 (a quarter of the electrons) where ISO 100 was meant: red std +104%
    "ISO 400": (lambda p: noisy_flat(p, iso=400), "std"),
    # the full well 4x too small (10,000 e-): red std +104%
    "full well 4x small": (lambda p: noisy_flat(p, noise=NoiseModel(full_well_e=NOISE_WELL / 4)), "std"),
    # no noise model applied (only 14-bit quantisation left): red std -100%
    "noise off": (lambda p: noisy_flat(p, noise=None), "std"),
    # the black level (512 of 16383 DN) not subtracted: mean +7.3%
    "black level kept": (lambda p: noisy_flat(p) * (WHITE - BLACK) / WHITE + BLACK / WHITE, "mean"),
    # the two greens summed, not averaged: mean +33%
    "greens summed": (lambda p: noisy_flat(p) * [1.0, 2.0, 1.0], "mean"),
}


@pytest.mark.parametrize("broken", list(NOISE_BROKEN))
def test_broken_noise_fails_the_bounds(tmp_path, broken):
    """A test of the test: the noisy DNG's bounds, run on a deliberately broken noise or decode, are missed."""
    make, bound = NOISE_BROKEN[broken]
    assert bound in noise_missed(make(tmp_path / "b.dng")), broken


# -- HDR merges -------------------------------------------------------------------------------------------------

def hdr_scene(h=96, w=160):
    """Half-res radiance (white-level units per second): 14-stop log ramp, a sun unsaturated only in the shortest
    frame, and a hotter sun saturated in every frame. Returns (radiance, sun mask, hot mask)."""
    yy, xx = np.mgrid[0:h, 0:w]
    colour = np.array([1.0, 0.8, 0.6])
    lmin = 0.01 / TIMES[-1]  # the darkest texel is 1% of saturation in the longest frame
    rad = (lmin * 2.0 ** (14 * xx / (w - 1)))[..., None] * colour
    sun = np.zeros((h, w), bool)
    sun[10:20, 10:30] = True
    rad[sun] = 0.7 / TIMES[0] * colour  # 70% of saturation in the shortest frame only
    hot = np.zeros((h, w), bool)
    hot[40:45, 10:20] = True
    rad[hot] = 3.0 / TIMES[0] * colour
    return rad, sun, hot


def test_raw_bracket_merge_recovers_radiance(tmp_path):
    rad, sun, hot = hdr_scene()
    paths = synth_bracket(tmp_path, block2(rad), TIMES, noise=NoiseModel(seed=1), make="Objcam", model="Synth")
    res = merge_raw_bracket(paths[::-1])  # any order
    truth = rad * TIMES[-1]  # units of the longest exposure
    assert res.units == "reference" and res.reference_time == TIMES[-1] and res.times == tuple(TIMES)
    rel = np.abs(res.radiance / truth - 1)
    ramp = ~sun & ~hot
    assert np.median(rel[ramp]) < 0.01  # measured ~0.5% (dark end ~2%, shot noise)
    assert np.median(rel[sun]) < 0.05  # measured ~0.4%
    assert np.array_equal(~res.valid, hot) and res.n_invalid == hot.sum()
    # saturated everywhere: the shortest frame's clipped value, a lower bound, never above the truth
    assert np.all(res.radiance[hot] <= truth[hot]) and np.all(res.radiance[hot] > 0.2 * truth[hot])
    per_s = merge_raw_bracket(paths, units="per_second")
    np.testing.assert_allclose(per_s.radiance * TIMES[-1], res.radiance, rtol=1e-5)
    # tests of the test (tests/broken.py): a "merge" of one frame, the longest (the sun and the ramp's bright half
    # clipped: ramp 9.2%, sun 99%) or the shortest (the ramp's dark half in the read noise: ramp 3.5%), misses a bound
    for name, frame in (("longest frame only", paths[-1]), ("shortest frame only", paths[0])):
        one = merge_raw_bracket([frame], units="per_second")
        bad = np.abs(one.radiance * TIMES[-1] / truth - 1)
        print(name, np.median(bad[ramp]), np.median(bad[sun]))
        assert not (np.median(bad[ramp]) < 0.01 and np.median(bad[sun]) < 0.05), name


def srgb_oetf(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def write_jpeg(path: Path, img8: np.ndarray, exif: dict | None = None) -> Path:
    import OpenImageIO as oiio

    h, w, _ = img8.shape
    spec = oiio.ImageSpec(w, h, 3, "uint8")
    spec.attribute("Compression", "jpeg:95")
    for k, v in (exif or {}).items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(img8))
    out.close()
    return path


def jpeg_bracket(tmp_path: Path) -> tuple[list[Path], np.ndarray]:
    """Five sRGB JPEGs (q95, 1% noise) of a 10-stop ramp (96 x 128), two stops apart, with their EXIF times.
    Returns (paths, radiance (96, 128, 3) in relative units)."""
    h, w = 96, 128
    yy, xx = np.mgrid[0:h, 0:w]
    rad = (2.0 ** (10 * xx / (w - 1) + 0.5 * yy / h))[..., None] * np.array([1.0, 0.85, 0.7])
    scale = 0.9 / (rad.max() * TIMES[0])
    rng = np.random.default_rng(0)
    paths = []
    for k, t in enumerate(TIMES):
        sig = rad * t * scale * (1 + 0.01 * rng.standard_normal(rad.shape))
        img8 = np.clip(np.rint(srgb_oetf(sig) * 255), 0, 255).astype(np.uint8)
        paths.append(write_jpeg(tmp_path / f"j{k}.jpg", img8, {"ExposureTime": float(t), "Make": "Objcam",
                                                               "Model": "JPEG", "FNumber": 8.0}))
    return paths, rad


# The Debevec merge's bounds (8-bit JPEGs), between the merge's measured values and the broken merges' below
JPEG_MEDIAN_REL = 0.05  # relative radiance after one global scale: measured 1.1%; broken 16-70%
JPEG_SPAN_TOL = 0.10  # the 9-stop ratio between the ramp's dark and bright ends: measured 0.1%; broken 33-96%
JPEG_CONVEX = 3.0  # response(255) / response(128): measured 5.0 (inverse sRGB 4.7); a linear response's 2.0


def jpeg_missed(res, resp: np.ndarray, rad: np.ndarray) -> list[str]:
    """The bounds above that a merge (``res``, its (256, 3) response) of the bracket of ``rad`` misses."""
    ratio = res.radiance / rad
    rel = np.abs(ratio / np.median(ratio) - 1)
    dark, bright = res.radiance[:, :8].mean() / rad[:, :8].mean(), res.radiance[:, -8:].mean() / rad[:, -8:].mean()
    print("jpeg merge: median", float(np.median(rel)), "span", float(bright / dark - 1), "convex",
          float(resp[255, 1] / resp[128, 1]))
    missed = [] if np.median(rel) < JPEG_MEDIAN_REL else ["median"]
    missed += [] if abs(bright / dark - 1) < JPEG_SPAN_TOL else ["span"]
    return missed + ([] if resp[255, 1] / resp[128, 1] > JPEG_CONVEX else ["convex"])


def test_jpeg_bracket_debevec(tmp_path):
    """Debevec's calibration and merge of a JPEG bracket recover the radiance. Broken variants
    (test_a_broken_jpeg_merge_fails_the_bounds): no calibration (a linear response), times one stop apart instead
    of two, one frame's time 3.9x off."""
    paths, rad = jpeg_bracket(tmp_path)
    assert exposure_time(paths[2]) == pytest.approx(TIMES[2], rel=1e-6)  # EXIF from the JPEGs
    res, resp = merge_ldr_bracket(paths)
    assert resp.shape == (256, 3) and np.all(np.diff(resp, axis=0) >= 0)
    # Debevec on 8-bit JPEGs: relative radiance within 5% (median) after one global scale, a 9-stop ratio between
    # the bright and dark ends within 10%, and a response convex like an inverse sRGB curve
    assert jpeg_missed(res, resp, rad) == []


class _LinearCalibrate:
    """A broken Debevec calibration: the identity response (the sRGB curve taken as linear)."""

    def process(self, imgs, times):
        return np.repeat(np.linspace(1.0 / 128, 255.0 / 128, 256, dtype=np.float32)[:, None, None], 3, axis=2)


# broken merges of the JPEG bracket: (how, the bounds they must miss at least one of, as measured)
BROKEN_JPEG = {
    "no response calibration (linear)": ("median", "span", "convex"),
    "EXIF times one stop apart (half the true spacing)": ("median", "span"),
    "the middle frame's time 3.9x too long (a wrong EXIF time)": ("median", "span"),
}


@pytest.mark.parametrize("broken", list(BROKEN_JPEG))
def test_a_broken_jpeg_merge_fails_the_bounds(tmp_path, monkeypatch, broken):
    """A test of the test (tests/broken.py): the same JPEG bracket merged with a linear response in place of
    Debevec's calibration, with exposure times one stop apart instead of two, or with the third frame's time
    3.9x too long, misses the bounds of test_jpeg_bracket_debevec (measured: median 16% / 70% / 28%, span -64% /
    -96% / +33%, response ratio 2.0 / 2.2 / 6.3)."""
    import cv2

    paths, rad = jpeg_bracket(tmp_path)
    times = None
    if broken.startswith("no response"):
        monkeypatch.setattr(cv2, "createCalibrateDebevec", lambda *a, **k: _LinearCalibrate())
    elif broken.startswith("EXIF times one stop"):
        times = [2.0 ** -12 * 2 ** k for k in range(5)]
    else:
        times = list(TIMES)
        times[2] = TIMES[2] * 3.9
    res, resp = merge_ldr_bracket(paths, times)
    missed = jpeg_missed(res, resp, rad)
    assert set(BROKEN_JPEG[broken]) & set(missed), (broken, missed)


# -- bad input --------------------------------------------------------------------------------------------------

def test_bad_raws_are_one_line_errors(tmp_path):
    good = write_dng(tmp_path / "good.dng", block2(ramp_signal(16, 16)), exposure_time=0.01)
    data = good.read_bytes()
    cases = {
        "truncated.dng": (data[: len(data) // 2], "truncated"),
        "header.dng": (data[:200], "truncated"),
        "zeroed.dng": (data[:1200] + bytes(1200) + data[2400:], "corrupt"),
        "notes.dng": (b"shopping list\n" * 50, "not an image"),
        "empty.dng": (b"", "empty"),
    }
    for name, (blob, word) in cases.items():
        p = tmp_path / name
        p.write_bytes(blob)
        with pytest.raises(InputError) as err:
            read_raw(p)
        assert_one_line_naming(err, p, word)
    p = tmp_path / "notes.jpg"
    p.write_bytes(b"not a jpeg")
    with pytest.raises(InputError) as err:
        read_ldr(p)
    assert_one_line_naming(err, p, "not an image")


def test_missing_exposure_and_mixed_brackets(tmp_path):
    import cv2

    p = tmp_path / "noexif.jpg"
    cv2.imwrite(str(p), np.full((8, 8, 3), 100, np.uint8))
    with pytest.raises(InputError) as err:
        exposure_time(p)
    assert_one_line_naming(err, p, "exposure time", MISSING_EXPOSURE_FIX)
    q = tmp_path / "noexif2.jpg"
    cv2.imwrite(str(q), np.full((8, 8, 3), 200, np.uint8))
    with pytest.raises(InputError) as err:
        merge_ldr_bracket([p, q])
    assert_one_line_naming(err, p, MISSING_EXPOSURE_FIX)
    assert exposure_time(p, override=0.5) == 0.5  # capture.toml wins

    sig = block2(np.full((12, 12, 3), 0.2))  # LibRaw refuses raws under 22 pixels a side
    a = write_dng(tmp_path / "a.dng", sig, exposure_time=0.01, make="Objcam", model="A")
    b = write_dng(tmp_path / "b.dng", block2(np.full((12, 16, 3), 0.2)), exposure_time=0.04, make="Objcam",
                  model="A")
    with pytest.raises(InputError) as err:
        merge_raw_bracket([a, b])
    assert_one_line_naming(err, b, "size", "a.dng")
    c = write_dng(tmp_path / "c.dng", sig, exposure_time=0.04, make="Other", model="B")
    with pytest.raises(InputError) as err:
        merge_raw_bracket([a, c])
    assert_one_line_naming(err, c, "cameras", "a.dng")
    d = write_dng(tmp_path / "d.dng", sig, exposure_time=0.04, make="Objcam", model="A", f_number=2.8)
    with pytest.raises(InputError) as err:
        merge_raw_bracket([a, d])
    assert_one_line_naming(err, d, "apertures")


UNDISTORT_MEDIAN, UNDISTORT_MAX = 0.001, 0.015  # absolute, on an image of values 1-3


def test_undistort_restores_the_pinhole_image():
    """A smooth pinhole image seen through OpenCV distortion (k1 k2 p1 p2 k3) and undistorted again matches the
    original inside the frame (bilinear resampling error only), and the corners that have no source are invalid."""
    import cv2

    from objcam.capture.photos import undistort

    h, w, f = 120, 160, 150.0
    dist = np.array([0.12, -0.05, 0.002, -0.001, 0.01])
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    pin = np.stack([np.sin(uu / 9.0) * np.cos(vv / 7.0) + 2.0, uu / w + 1.0, vv / h + 1.0], axis=2).astype(np.float32)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    # the distorted photo: each of its pixels shows the pinhole image where its ray points
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1)[:, None, :]
    und = cv2.undistortPoints(pts, K, dist, P=K).reshape(h, w, 2).astype(np.float32)
    photo = cv2.remap(pin, und[..., 0], und[..., 1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    out, valid = undistort(photo, None, f, dist)
    inner = np.zeros((h, w), bool)
    inner[15:-15, 20:-20] = True
    err = np.abs(out - pin)[inner & valid]
    # measured: median 0.00028, max 0.0072 (was < 0.01 / < 0.08, which the photo left distorted met in median)
    assert np.median(err) < UNDISTORT_MEDIAN and err.max() < UNDISTORT_MAX
    assert valid[h // 2, w // 2] and valid[inner].mean() > 0.99
    # a test of the test (tests/broken.py): the photo left distorted (median 0.0028, max 0.18), and undistorted
    # with the tangential terms dropped (k1 k2 k3 only: max 0.023), miss the bounds
    radial, _ = undistort(photo, None, f, dist * [1, 1, 0, 0, 1])
    for name, img in (("not undistorted", photo), ("tangential terms dropped", radial)):
        bad = np.abs(img - pin)[inner & valid]
        assert not (np.median(bad) < UNDISTORT_MEDIAN and bad.max() < UNDISTORT_MAX), name


def test_one_exposure_time_for_a_folder_without_exif(tmp_path):
    """[camera] exposure_time: every photo without an EXIF exposure time takes it; EXIF and exposure_times win,
    and an EXR (already linear) never takes it."""
    from objcam.capture.photos import time_override
    from objcam.image_io import write_exr
    from objcam.schemas.capture import CameraFacts

    bare = write_jpeg(tmp_path / "a.jpg", np.full((8, 8, 3), 100, np.uint8))
    shot = write_jpeg(tmp_path / "b.jpg", np.full((8, 8, 3), 100, np.uint8), {"ExposureTime": 0.004})
    write_exr(tmp_path / "c.exr", np.ones((4, 4, 3), np.float32))
    facts = CameraFacts(exposure_time=0.02, exposure_times={"c.jpg": 0.5})
    assert time_override(bare, facts.exposure_times, tmp_path, facts.exposure_time) == 0.02
    assert time_override(shot, facts.exposure_times, tmp_path, facts.exposure_time) is None  # EXIF's 1/250
    assert exposure_time(shot, time_override(shot, {}, tmp_path, 0.02)) == pytest.approx(0.004)
    assert time_override(tmp_path / "c.exr", {}, tmp_path, 0.02) is None
    assert time_override(bare, {"a.jpg": 0.1}, tmp_path, 0.02) == 0.1
    with pytest.raises(ValueError):
        CameraFacts(exposure_time=0)
