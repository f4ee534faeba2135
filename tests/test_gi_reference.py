"""bench.gi_reference on an existing capture (``--capture``): the A a hard-suite capture already holds, measured
against path-traced columns through that capture's own camera (issue 22, item 2: is A right at grazing light?)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.gi_reference import column_errors, energy_ratios, part_errors


def test_energy_ratio_and_column_error_of_known_columns():
    rng = np.random.default_rng(0)
    r = rng.uniform(0.5, 1.5, (3, 50))
    ref = {"ref_a": r, "ref_b": r}  # no reference noise
    A = np.stack([r[0], 1.1 * r[1], r[2][::-1]], axis=1)  # exact, 10% bright, right energy in the wrong pixels
    assert energy_ratios(A, np.array([0, 1, 2]), ref) == pytest.approx([1.0, 1.1, 1.0])
    assert energy_ratios(A, np.array([-1]), ref) == [0.0]  # a texel A dropped lights nothing
    _, per = column_errors(A, np.array([0, 1, 2]), ref)
    assert per[0] == pytest.approx(0.0) and per[1] == pytest.approx(0.1) and per[2] > 0.2


def test_the_column_error_splits_into_the_objects_pixels_and_the_supports():
    """A 10% too bright on the first 10 pixels (the "object") only: its part's error is 10%, the support's 0, and
    the whole's lies between (a split that mixed the parts up, or ignored ``on_object``, fails)."""
    rng = np.random.default_rng(1)
    r = rng.uniform(0.5, 1.5, (2, 40))
    ref = {"ref_a": r, "ref_b": r}
    A = r.T.copy()
    A[:10] *= 1.1
    on_object = np.arange(40) < 10
    parts = part_errors(A, np.array([0, 1]), ref, on_object)
    assert parts["object"] == pytest.approx(0.1) and parts["support"] == pytest.approx(0.0, abs=1e-12)
    whole, _ = column_errors(A, np.array([0, 1]), ref)
    assert 0.0 < whole < 0.1


def test_a_hard_capture_is_measured_through_its_own_camera(tmp_path, capsys):
    """A tiny hard-suite capture (32 x 32, objcam's default A built by ``objcam run``): two columns of the row just
    above the horizon match the reference's light to a few percent; the same reference against A's columns a
    quarter turn away misses (a test of the measure)."""
    from bench.gi_reference import main
    from objcam.transport import load_transport
    from tests.hard_capture import tiny_hard_capture

    cap, _ = tiny_hard_capture(tmp_path, 35.0)
    tr = load_transport(cap / "objcam" / "transport", "lamp30_r0_n0.5")
    h = tr.env_height
    out = tmp_path / "gi"
    grazing = h // 2 - 1  # the row just above the horizon
    assert main(["--capture", str(cap), "--rows", str(grazing), "--columns", "2", "--spp", "64", "--max-depth", "3",
                 "--out", str(out)]) == 0
    assert "the capture's A" in capsys.readouterr().out
    res = json.loads(next(out.glob("gi-cap-*.json")).read_text())
    assert res["target"] == "lamp30_r0_n0.5" and [r for r, _ in res["texels"]] == [grazing, grazing]
    row = res["rows"][0]
    assert row["energy_ratio"] == pytest.approx([1.0, 1.0], abs=0.05), row
    assert row["column_error"] < 0.1, row
    # the test of the test: the same reference against the columns a quarter turn (h / 2 columns) round
    ref = dict(np.load(next(out.glob("reference-cap-*.npz"))))
    pos = {int(t): i for i, t in enumerate(tr.texel_index)}
    turned = np.array([pos[r * 2 * h + (c + h // 2) % (2 * h)] for r, c in res["texels"]])
    err_turned, _ = column_errors(np.asarray(tr.A.mean(axis=0), np.float64), turned, ref)
    assert err_turned > 3 * row["column_error"] and err_turned > 0.2
