"""The transport's memory and time estimate (objcam.transport.budget) against what the builds and solves used, and
its refusal with a small fake machine."""

from __future__ import annotations

import pytest

from objcam.errors import StageError
from objcam.transport import budget


def test_kept_texels_match_the_demo_transports():
    # measured: A keeps 1,088 texels at 32 x 64 and 4,224 at 64 x 128 above the demo's support plane
    assert budget.kept_texels(32, True) == 1088 and budget.kept_texels(64, True) == 4224
    assert budget.kept_texels(32, False) == 2048 and budget.kept_texels(2, True) == 8  # both rows


def test_estimate_parts_and_scaling():
    e = budget.estimate(16384, 4224, 1)
    p = e["parts"]
    assert p["a_bytes"] == 4 * 16384 * 4224 and p["gram_bytes"] == 8 * 4224**2
    assert e["bytes"] == p["a_bytes"] + p["gram_bytes"] + p["solve_bytes"]
    # measured on the demo capture at 64 x 128 (direct A, loaded 2-core machine): A 91 s, the edge solve on its
    # PCG path 7.5-11.0 s of CPU (session 18; the verdict ~0.5 s); the estimate is within 2.5x of A (its rate was
    # measured at 32 x 64, where fewer pairs need refining) and 1.5x of the solve
    assert 91 / 2.5 < p["a_seconds"] < 91 * 2.5 and 7.5 / 1.5 < p["solve_seconds"] < 11.0 * 1.5
    # 128 x 256 (forest capture, quiet machine, 2026-12-04): the solve 140 s of CPU and its verdict 21-35 s
    e2 = budget.estimate(16384, budget.kept_texels(128, True), 1)
    assert 161 / 1.5 < e2["parts"]["solve_seconds"] < 175 * 1.5
    assert budget.estimate(16384, 16640, 1, targets=4)["parts"]["solve_seconds"] == pytest.approx(
        4 * e2["parts"]["solve_seconds"])  # the targets are solved one after another
    # broken: the Cholesky path's cubic rate (3.3e-10 s per texel^3, the model before the PCG solve) misses both
    assert not 161 / 1.5 < 3.3e-10 * 16640**3 < 175 * 1.5 and not 7.5 / 1.5 < 3.3e-10 * 4224**3 < 11.0 * 1.5
    # the Gram matrix grows 16x, A 4x
    assert e2["parts"]["gram_bytes"] / p["gram_bytes"] == pytest.approx((16640 / 4224) ** 2)
    # the solve stage's peak at 128 x 256 (demo capture, direct A: 7,131,232 KiB RSS, session 24): the estimate
    # holds it, within 1.5x; broken: the old 5 copies (each solve forming its own Q) are 2x it
    peak = 7131232 * 1024
    assert peak < e2["bytes"] < 1.5 * peak
    assert not e2["bytes"] + 2 * e2["parts"]["gram_bytes"] < 1.5 * peak


def test_refusal_names_the_numbers_and_the_parameter(tmp_path):
    e = budget.estimate(16384, 4224, 1)
    budget.check(e, tmp_path / "capture.toml", memory=8 * 2**30)  # fits: nothing raised
    with pytest.raises(StageError) as info:
        budget.check(e, tmp_path / "capture.toml", memory=2**29)  # a fake 0.5 GiB machine
    msg = str(info.value)
    assert "\n" not in msg and "transport.env_height" in msg and "4,224 texels" in msg and "0.5 GiB" in msg
    assert "capture.toml" in msg
