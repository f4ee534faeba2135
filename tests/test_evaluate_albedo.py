"""evaluate's albedo scoring (issue 29): with a pinned scale (pixels of known albedo) an albedo is scored as it is,
so a deliberately biased albedo shows its bias; the fitted-scale figures are reported beside, named as such; an
ambiguous scale is still scored after the per-channel scale. truth.json's albedo forms: a number, an RGB list,
{rgb: ...} or {texture: ...}; anything else is one line naming the file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from objcam.errors import InputError
from objcam.metrics import albedo_metrics
from objcam.truth import truth_albedo_entry


def _biased(bias: float = 1.18):
    """A textured true albedo (32 x 32, values 0.3 .. 0.8) and an estimate that is the truth x ``bias`` plus a
    little noise: the issue's support, 18% too bright."""
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:32, :32]
    truth = np.repeat((0.55 + 0.25 * np.sin(xx / 4.0) * np.cos(yy / 5.0))[..., None], 3, axis=2)
    est = np.clip(truth * bias + rng.normal(0, 0.005, truth.shape), 0, 1)
    mask = np.ones((32, 32), bool)
    mask[:4] = False  # the object's pixels: albedo known, not estimated
    return est, truth, mask


def test_pinned_scale_scores_the_albedo_as_it_is():
    est, truth, mask = _biased(1.18)
    d = est[mask] - truth[mask]
    unscaled = float(np.sqrt(np.mean(d * d)) / truth[mask].mean())
    pinned = albedo_metrics(est, truth, mask, pinned=True)
    assert pinned["albedo_relative_rmse"] == pytest.approx(unscaled, rel=1e-12)
    assert unscaled > 0.17  # the 18% bias, not hidden
    assert pinned["albedo_scale"] == [1.0, 1.0, 1.0] and pinned["albedo_scored_as"] == "as estimated"
    assert pinned["albedo_relative_rmse_unscaled"] == pinned["albedo_relative_rmse"]
    # beside it, named as such: what a fitted per-channel scale would hide (the scale ~ 1 / 1.18)
    assert pinned["albedo_relative_rmse_fitted_scale"] < 0.02
    np.testing.assert_allclose(pinned["albedo_fitted_scale"], 1 / 1.18, rtol=0.01)
    np.testing.assert_allclose(pinned["albedo_mean_ratio"], 1.18, rtol=0.01)
    assert pinned["albedo_ssim"] < pinned["albedo_ssim_fitted_scale"]


def test_ambiguous_scale_is_scored_after_the_fitted_scale():
    est, truth, mask = _biased(1.18)
    amb = albedo_metrics(est, truth, mask, pinned=False)
    assert amb["albedo_scored_as"] == "fitted scale"
    assert amb["albedo_relative_rmse"] == amb["albedo_relative_rmse_fitted_scale"] < 0.02
    assert amb["albedo_scale"] == amb["albedo_fitted_scale"]
    assert amb["albedo_relative_rmse_unscaled"] > 0.17
    # an unbiased estimate scores the same either way (to the noise)
    est1, truth1, mask1 = _biased(1.0)
    a, b = albedo_metrics(est1, truth1, mask1, pinned=True), albedo_metrics(est1, truth1, mask1, pinned=False)
    assert a["albedo_relative_rmse"] == pytest.approx(b["albedo_relative_rmse"], rel=0.05)


@pytest.mark.parametrize("form, rgb", [
    ([0.8, 0.7, 0.6], [0.8, 0.7, 0.6]),
    ({"rgb": [0.8, 0.7, 0.6]}, [0.8, 0.7, 0.6]),
    ({"rgb": 0.5}, [0.5, 0.5, 0.5]),
    (0.25, [0.25, 0.25, 0.25]),
    ([1, 0, 0], [1.0, 0.0, 0.0]),
])
def test_truth_albedo_forms(tmp_path, form, rgb):
    assert truth_albedo_entry(form, "support", tmp_path) == {"rgb": rgb}


def test_truth_albedo_texture_and_absent(tmp_path):
    tex = {"texture": "truth/albedo_support.exr", "extent": 0.3}
    assert truth_albedo_entry(tex, "support", tmp_path) == tex
    assert truth_albedo_entry(None, "support", tmp_path) is None


@pytest.mark.parametrize("bad", [[0.8, 0.8], "grey", {"rgb": [0.1, "x", 0.2]}, [True, 0.1, 0.1], {"colour": 1},
                                 [float("nan"), 0.1, 0.1]])
def test_truth_albedo_bad_forms_are_one_line(tmp_path, bad):
    with pytest.raises(InputError) as e:
        truth_albedo_entry(bad, "support", tmp_path)
    msg = str(e.value)
    assert "truth.json" in msg and "albedo.support" in msg and "\n" not in msg
    json.dumps(bad)  # the forms are what a JSON file can hold
