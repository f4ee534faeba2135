"""bench.photographed_sweep's verdict on its rows (the captures themselves run in `make bench BENCH=sweep`)."""

from __future__ import annotations

from bench.photographed_sweep import failures, markdown, silent_targets


def _row(case, ssim, flat, grade, **kw):
    t = {"ssim": ssim, "flat_ssim": flat, "row_mean_ssim": flat + 0.1, "grade": grade,
         "brightest_angle_deg": 1.0, "albedo_relative_rmse": 0.03}
    silent = silent_targets({"t0": t})
    return {"case": case, "varies": "x", "exit": 0, "positions": [], "silhouette_agreement": 0.8,
            "targets": {"t0": t}, "silent": silent, **kw}


def test_a_silent_map_or_a_traceback_fails_the_sweep_and_a_refusal_does_not():
    rows = [_row("good", 0.7, 0.5, "yellow"), _row("honest_red", 0.3, 0.5, "red"),
            {"case": "refused", "varies": "x", "exit": 2, "error": "object.ply: ... -- fix: ...", "traceback": False}]
    assert failures(rows) == []
    md = markdown(rows, "header")
    assert "silent (finished, a target no better than the flat map and not red): none" in md
    assert "refused with a one-line error: refused" in md
    bad = rows + [_row("quiet", 0.3, 0.5, "yellow"),
                  {"case": "crash", "varies": "x", "exit": 2, "error": "stage sfm failed", "traceback": True}]
    assert failures(bad) == ["quiet", "crash"]
    md = markdown(bad, "header")
    assert "silent (finished, a target no better than the flat map and not red): quiet (t0)" in md
    assert "failed with a traceback: crash" in md


def test_silent_means_no_better_than_a_flat_map_and_not_red():
    t = {"ssim": 0.30, "flat_ssim": 0.30, "grade": "yellow"}
    assert silent_targets({"a": t}) == ["a"]
    assert silent_targets({"a": t | {"grade": "red"}, "b": t | {"ssim": 0.31}}) == []


def test_the_one_colour_copy_declares_the_object_and_links_the_photos(tmp_path):
    import os

    import pytest

    from bench.photographed_sweep import CASES, ONE_COLOUR, one_colour_capture
    from objcam.schemas.capture import UniformAlbedo

    full = tmp_path / "full"
    (full / "views").mkdir(parents=True)
    (full / "objcam").mkdir()
    (full / "views" / "v0.dng").write_bytes(b"raw")
    (full / "objcam" / "cache").write_bytes(b"x")
    toml = '[scene]\nobject = "object.ply"\n\n[camera]\nwhite_balance = "camera"\n'
    (full / "capture.toml").write_text(toml)
    dest = one_colour_capture(full, tmp_path / "one")
    import tomllib

    doc = tomllib.loads((dest / "capture.toml").read_text())
    assert doc["albedo"] == {"object": "uniform"} and doc["camera"] == {"white_balance": "camera"}
    assert os.path.samefile(dest / "views" / "v0.dng", full / "views" / "v0.dng")
    assert not (dest / "objcam").exists() and (full / "capture.toml").read_text() == toml  # inputs untouched
    from objcam.schemas.capture import AlbedoSection

    assert isinstance(AlbedoSection(**doc["albedo"]).object, UniformAlbedo)
    assert set(ONE_COLOUR.values()) <= set(CASES) and set(ONE_COLOUR) <= set(CASES)
    (full / "capture.toml").write_text(toml + "\n[albedo]\nobject = 0.6\n")
    with pytest.raises(ValueError, match="albedo is unknown"):
        one_colour_capture(full, tmp_path / "two")
