"""Issue 22 item 4: negative pixel values are data. Zero-mean noise passes the scene stage (kept, not clipped) and
solves; negatives far beyond the noise, or a large negative area, are refused; an HDRI with tiny negatives is
clamped with a note, one with a large negative area refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.errors import InputError
from objcam.image_io import read_exr, write_exr
from objcam.pipeline.cli import main
from objcam.synth.assets import load_envmap
from tests.test_bad_input import TOML, assert_one_line_error, make_capture, run_scene

H, W = 24, 32


def _noisy(mean: float = 0.02, sigma: float = 0.01, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (mean + rng.normal(0.0, sigma, (H, W, 3))).astype(np.float32)


def test_zero_mean_noise_with_negatives_passes_and_solves(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap", size=(W, H))
    img = _noisy()
    assert (img < 0).mean() > 0.01  # a few percent of the values are negative: honest noise around a dark level
    write_exr(cap / "targets" / "t0.exr", img)
    code = main(["run", str(cap), "--quiet", "--until", "solve", "--set", "transport.env_height=8",
                 "--set", "transport.model=direct"])
    assert code == 0, capsys.readouterr().err
    kept = read_exr(cap / "objcam" / "scene" / "targets" / "t0" / "image.exr")
    np.testing.assert_array_equal(kept, img)  # negatives kept: clipping would bias the dark pixels up
    rec = json.loads((cap / "objcam" / "scene" / "stage.json").read_text())
    assert rec["metrics"]["target_checks"]["t0"]["negative_pixels"] > 0
    assert "negative pixel(s) kept" in rec["summary"]
    env = read_exr(cap / "objcam" / "solve" / "t0" / "envmap.exr")
    assert np.all(np.isfinite(env)) and env.max() > 0


@pytest.mark.parametrize("noise_sigma", [None, 0.5])  # estimated, or given (relative to the median: 0.01 abs)
def test_negatives_far_beyond_the_noise_are_refused(tmp_path, capsys, noise_sigma):
    cap = make_capture(tmp_path / "cap", size=(W, H))
    if noise_sigma is not None:
        (cap / "capture.toml").write_text(TOML + f"noise_sigma = {noise_sigma}\n")
    img = _noisy()
    img[5:11, 5:11] -= 0.1  # a wrong black level over a patch: -8 sigma
    write_exr(cap / "targets" / "t0.exr", img)
    code, err = run_scene(cap, capsys)
    assert_one_line_error(code, err, "t0.exr", "far beyond its noise", "sigma")


def test_large_negative_area_within_few_sigma_is_refused(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap", size=(W, H))
    img = _noisy()
    img[:, : W // 3] -= 0.045  # a third of the image offset to -2.5 sigma on average: many pixels below -3 sigma
    write_exr(cap / "targets" / "t0.exr", img)
    code, err = run_scene(cap, capsys)
    assert code == 2, err
    assert "t0.exr" in err and ("large negative area" in err or "far beyond" in err)


def _env(path, neg_texels: int, depth: float) -> None:
    env = np.ones((16, 32, 3), np.float32)
    env.reshape(-1, 3)[:neg_texels, 0] = -depth
    write_exr(path, env)


def test_hdri_with_tiny_negatives_is_clamped_with_a_note(tmp_path):
    _env(tmp_path / "sky.exr", 3, 0.004)
    notes: list[str] = []
    env = load_envmap(str(tmp_path / "sky.exr"), notes=notes)
    assert env.min() == 0.0 and env.max() == 1.0
    assert len(notes) == 1 and "3 slightly negative texel(s)" in notes[0] and "clamped" in notes[0]


@pytest.mark.parametrize("texels,depth", [(100, 0.004), (3, 0.5)])  # 20% of the texels; or deep
def test_hdri_with_a_large_negative_area_is_refused(tmp_path, texels, depth):
    _env(tmp_path / "sky.exr", texels, depth)
    with pytest.raises(InputError, match="large negative area"):
        load_envmap(str(tmp_path / "sky.exr"))
