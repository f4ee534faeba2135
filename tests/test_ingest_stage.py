"""Stage ``ingest`` through the CLI: DNG brackets of a known radiance map merge back to it, pixels saturated in every
frame are flagged, the view copies keep their radiance, and bad input stops with one line naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from objcam.capture.dng import NoiseModel, synth_bracket, write_dng

WB = (2.0, 1.0, 1.5)
TIMES = [2.0 ** -k for k in (10, 8, 6, 4, 2)]  # 5 frames, 2 EV apart: 1/1024 .. 1/4 s
H, W = 40, 60  # decoded (superpixel) size; the sensor is 80 x 120


def radiance_map() -> np.ndarray:
    """(H, W, 3) per-second radiance in white-level units: a 4-decade ramp along x, colour along y, and a 'sun'
    (4 x 4 pixels) that saturates even the shortest frame."""
    x = np.logspace(-0.5, 2.9, W)  # 0.3 .. 800 per second: only the 1/1024 s frame holds the top unsaturated
    rad = x[None, :, None] * np.array([1.0, 0.8, 0.6])[None, None, :] * np.linspace(0.7, 1.0, H)[:, None, None]
    rad[2:6, 2:6] = 5e4  # x 1/1024 s = 49 > 1: saturated in every frame
    return rad.astype(np.float64)


def block2(img: np.ndarray) -> np.ndarray:
    return img.repeat(2, 0).repeat(2, 1)


def write_capture(root: Path, noise: NoiseModel | None = NoiseModel(full_well_e=50000.0, seed=3)) -> np.ndarray:
    """A photographed capture with one bracketed target (DNGs), two DNG views and [scale]; returns the radiance."""
    rad = radiance_map()
    # the sensor sees radiance / wb per channel; the camera's as-shot white balance undoes it
    synth_bracket(root / "targets" / "t0", block2(rad / np.array(WB)), TIMES, noise=noise, wb=WB)
    view = np.clip(rad / rad.max() * 300, 0, None)  # view exposure: 1/100 s, nothing saturated
    view[2:6, 2:6] = 10.0
    for i in range(2):
        write_dng(root / "views" / f"v{i}.dng", block2(view / np.array(WB)) * 0.01 * (1 + i), exposure_time=0.01,
                  wb=WB)
    (root / "t0.json").write_text(json.dumps({"width": W, "height": H, "fx": 50.0, "fy": 50.0, "cx": 29.5,
                                               "cy": 19.5, "world_from_camera": np.eye(4).tolist()}))
    (root / "capture.toml").write_text(
        '[scene]\nobject = "object.ply"\n\n[camera]\nwhite_balance = "camera"\n\n[views]\nfolder = "views"\n'
        'max_size = 200\n\n[scale]\nobject_height = 0.1\n\n[[targets]]\nname = "t0"\nfolder = "targets/t0"\n'
        'camera = "t0.json"\n')
    return rad


def run_ingest(capture: Path, work: Path, capsys) -> tuple[int, str]:
    from objcam.pipeline.cli import main

    rc = main(["ingest", str(capture), "--work", str(work), "-q"])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("noisy", [False, True])
def test_bracket_merge_recovers_radiance(tmp_path, capsys, noisy):
    """Noise-free raws: every unsaturated texel within 1% of the true radiance (only 14-bit quantisation is
    left). With shot and read noise (50,000 e- full well): unbiased, median error well under 1%. Broken variant,
    asserted below: the merge 1.5% too bright."""
    import cv2

    from objcam.image_io import read_exr

    cap = tmp_path / "cap"
    rad = write_capture(cap, noise=NoiseModel(full_well_e=50000.0, seed=3) if noisy else None)
    before = {p: p.stat().st_mtime_ns for p in cap.rglob("*")}
    rc, err = run_ingest(cap, tmp_path / "work", capsys)
    assert rc == 0, err
    d = tmp_path / "work" / "ingest" / "targets" / "t0"
    img = read_exr(d / "image.exr")
    valid = cv2.imread(str(d / "valid.png"), cv2.IMREAD_UNCHANGED) > 127
    assert img.shape == (H, W, 3) and valid.shape == (H, W)
    # pixels saturated in every frame: exactly the sun, flagged, kept as a finite lower bound (not clipped to 0)
    sun = np.zeros((H, W), bool)
    sun[2:6, 2:6] = True
    assert np.array_equal(~valid, sun)
    assert np.all(np.isfinite(img[sun])) and np.all(img[sun] > 0) and np.all(img[sun] <= rad[sun])
    def missed(merged: np.ndarray) -> bool:
        ratio = merged[valid] / rad[valid]
        rel = np.abs(ratio - 1)
        if noisy:  # measured: median 0.5%, mean ratio 1.000 (per-pixel noise reaches 2-8% on the darkest texels)
            return not (np.median(rel) < 0.01 and abs(ratio.mean() - 1) < 0.002)
        return not rel.max() < 0.01  # measured: max 0.2%

    assert not missed(img)
    # a test of the test (tests/broken.py): a merge 1.5% too bright (exposure times 1.5% short) misses the bounds
    assert missed(img * 1.015)
    meta = json.loads((d / "merge.json").read_text())
    assert meta["exposure_times_s"] == pytest.approx(TIMES) and meta["n_invalid"] == 16
    assert meta["reader"] == "rawpy superpixel" and meta["white_balance"] == pytest.approx(list(WB), rel=1e-4)
    assert cv2.imread(str(d / "sfm.png")).shape == (H, W, 3)
    # the capture folder is untouched
    assert {p: p.stat().st_mtime_ns for p in cap.rglob("*")} == before


def test_views_copies_and_record(tmp_path, capsys):
    """The view copies are per second and white-balanced: v1 (twice v0's light) reads 2x v0 to 0.1%. Broken
    variants, asserted below: v1's time misread (1/80 s), each copy scaled to its own maximum, v1 0.2% off."""
    from objcam.image_io import read_exr

    cap = tmp_path / "cap"
    write_capture(cap, noise=None)
    (cap / "capture.toml").write_text((cap / "capture.toml").read_text().replace("max_size = 200",
                                                                                  "max_size = 200"))
    rc, err = run_ingest(cap, tmp_path / "work", capsys)
    assert rc == 0, err
    out = tmp_path / "work" / "ingest"
    recs = json.loads((out / "views.json").read_text())
    assert [r["name"] for r in recs] == ["v0", "v1"]
    r = recs[1]
    assert (r["width"], r["height"], r["scale"]) == (W, H, 1.0) and r["source"] == "views/v1.dng"
    assert r["exposure"] == {"time_s": pytest.approx(0.01), "iso": 100.0, "f_number": pytest.approx(8.0)}
    v0, v1 = read_exr(out / "views" / "v0.exr"), read_exr(out / "views" / "v1.exr")
    # per second and white-balanced: v1 got twice the light of v0 (measured ratio 2.0000)
    def ratio_missed(a: np.ndarray, b: np.ndarray) -> bool:
        return not np.median(b / np.maximum(a, 1e-9)) == pytest.approx(2.0, rel=1e-3)

    assert not ratio_missed(v0, v1)
    # a test of the test (tests/broken.py), each missing the bound: v1's time read as 1/80 s for 1/100 s (a wrong
    # EXIF rational, ratio 1.6); each copy scaled to its own maximum (an auto exposure, ratio 1.0); v1's time off
    # by 0.2% (ratio 2.004)
    for broken in (v1 * 0.01 / 0.0125, v1 * v0.max() / v1.max(), v1 * 1.002):
        assert ratio_missed(v0, broken), np.median(broken / np.maximum(v0, 1e-9))
    import cv2

    png = cv2.imread(str(out / "views" / "v0.png"))
    assert png.shape == (H, W, 3) and png.dtype == np.uint8 and png.max() > 200
    assert (out / "views_valid" / "v0.png").is_file()


def test_views_downsampled_to_max_size(tmp_path, capsys):
    """A view larger than max_size is area-averaged to it, keeping its mean radiance to 1e-4. Broken variants,
    asserted below: the time or white balance left in, an sRGB copy, nearest-pixel and unfiltered bilinear shrinks."""
    from objcam.image_io import read_exr

    cap = tmp_path / "cap"
    cap.mkdir()
    rng = np.random.default_rng(0)
    big = rng.uniform(0.05, 0.5, (150, 250, 3))  # decoded 250 x 150 -> copy 200 x 120
    write_dng(cap / "views" / "a.dng", block2(big) / np.array(WB), exposure_time=0.5, wb=WB)
    write_capture(cap / "other")
    for sub in ("targets", "t0.json", "capture.toml"):
        shutil.move(str(cap / "other" / sub), str(cap / sub))
    rc, err = run_ingest(cap, tmp_path / "work", capsys)
    assert rc == 0, err
    rec = json.loads((tmp_path / "work" / "ingest" / "views.json").read_text())[0]
    assert (rec["width"], rec["height"], rec["photo_width"]) == (200, 120, 250) and rec["scale"] == 0.8
    img = read_exr(tmp_path / "work" / "ingest" / "views" / "a.exr")
    assert img.shape == (120, 200, 3)
    # area averaging keeps radiance: measured mean off by 2e-7 (14-bit rounding and float32 sums); bound 1e-4
    # (was 1%, which passed a copy shrunk by nearest pixel or unfiltered bilinear)
    def mean_missed(copy: np.ndarray) -> bool:
        return not copy.mean() == pytest.approx(big.mean() / 0.5, rel=1e-4)

    assert not mean_missed(img)
    # a test of the test (tests/broken.py), each missing the bound: the copy not divided by its 0.5 s (-50%), not
    # white-balanced (the sensor's values, -28%), sRGB-encoded like the PNG preview (+38%), shrunk by nearest
    # pixel (+5.9e-4) or by unfiltered bilinear (+1.5e-4) instead of area averaging (the last two made from the
    # true radiance, so they carry no DNG rounding)
    import cv2

    srgb = np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.clip(img, 0.0031308, None) ** (1 / 2.4) - 0.055)
    shrunk = [cv2.resize(big / 0.5, (200, 120), interpolation=m) for m in (cv2.INTER_NEAREST, cv2.INTER_LINEAR)]
    for broken in (img * 0.5, img / np.array(WB), srgb, *shrunk):
        assert mean_missed(broken), broken.mean() / (big.mean() / 0.5)


# ------------------------------------------------------------------------------------------------ bad input


def _one_line(err: str, *words: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("objcam: error:")]
    assert len(lines) == 1, err
    for w in words:
        assert w.lower() in lines[0].lower(), lines[0]
    assert "fix:" in lines[0]


def test_bad_inputs_name_the_file(tmp_path, capsys):
    cap = tmp_path / "cap"
    write_capture(cap, noise=None)
    frames = sorted((cap / "targets" / "t0").glob("*.dng"))

    # a truncated raw
    data = frames[1].read_bytes()
    frames[1].write_bytes(data[: len(data) // 3])
    rc, err = run_ingest(cap, tmp_path / "w1", capsys)
    assert rc == 2
    _one_line(err, str(frames[1]))
    assert not (tmp_path / "w1" / "ingest").exists()  # nothing half-written
    frames[1].write_bytes(data)

    # a bracket frame of another size
    write_dng(frames[2], np.full((2 * H + 4, 2 * W, 3), 0.1), exposure_time=TIMES[2], wb=WB)
    rc, err = run_ingest(cap, tmp_path / "w2", capsys)
    assert rc == 2
    _one_line(err, frames[2].name, "bracket mixes")

    # a frame from another camera
    write_dng(frames[2], np.full((2 * H, 2 * W, 3), 0.1), exposure_time=TIMES[2], wb=WB, model="other body")
    rc, err = run_ingest(cap, tmp_path / "w3", capsys)
    assert rc == 2
    _one_line(err, frames[2].name, "bracket mixes cameras")
    frames[2].unlink()

    # a linear TIFF without EXIF: no exposure time, then the override in capture.toml fixes it
    import cv2

    tif = cap / "targets" / "t0" / "extra.tif"
    cv2.imwrite(str(tif), np.full((H, W, 3), 1000, np.uint16))
    for f in frames:
        if f.exists():
            f.unlink()
    rc, err = run_ingest(cap, tmp_path / "w4", capsys)
    assert rc == 2
    _one_line(err, str(tif), "no exposure time")
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('[camera]\n', '[camera]\nexposure_times = { "extra.tif" = 0.5 }\n'))
    rc, err = run_ingest(cap, tmp_path / "w4", capsys)
    assert rc == 0, err

    # an empty folder
    tif.unlink()
    rc, err = run_ingest(cap, tmp_path / "w5", capsys)
    assert rc == 2
    _one_line(err, str(cap / "targets" / "t0"), "no photos")


def test_distortion_needs_focal_length(tmp_path, capsys):
    cap = tmp_path / "cap"
    write_capture(cap, noise=None)
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('[camera]\n', '[camera]\ndistortion = [0.5, 0.0, 0.0, 0.0]\n'))
    rc, err = run_ingest(cap, tmp_path / "w", capsys)
    assert rc == 2
    _one_line(err, str(toml), "focal_px")
    toml.write_text(toml.read_text().replace('[camera]\n', '[camera]\nfocal_px = 80.0\n'))
    rc, err = run_ingest(cap, tmp_path / "w", capsys)
    assert rc == 0, err
    import cv2

    from objcam.image_io import read_exr

    # pincushion distortion removed: the corners of the undistorted frame map outside the photo: invalid
    d = tmp_path / "w" / "ingest" / "targets" / "t0"
    valid = cv2.imread(str(d / "valid.png"), cv2.IMREAD_UNCHANGED) > 127
    assert read_exr(d / "image.exr").shape == (H, W, 3)
    assert json.loads((d / "merge.json").read_text())["undistorted"] is True
    assert valid[H // 2, W // 2] and not valid[0, 0]
