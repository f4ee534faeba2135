"""Exposure checks on a merged chrome-ball bracket (objcam.probe.exposure), against brackets of a known image.

The probe stage reads ingest's merge (image.exr in per-second units, valid.png, merge.json's times) without the
per-frame counts, so the frames' levels are recovered from the merged radiance; here they are checked against
the merge's own counts.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from objcam.errors import InputError
from objcam.probe.exposure import DIM_MEDIAN, check_bracket, dim_warning, frames_used, longest_level
from objcam.synth.probe import make_bracket


def _scene(median: float = 1.0) -> np.ndarray:
    """(64, 96, 3) radiance spanning 6 decades (log-uniform), median ``median``."""
    rng = np.random.default_rng(0)
    lum = 10.0 ** rng.uniform(-3, 3, (64, 96))
    lum *= median / np.median(lum)
    return np.repeat(lum[..., None], 3, axis=2) * np.array([1.0, 0.8, 0.6])


def _as_ingest(merge) -> SimpleNamespace:
    """What the probe stage has of ``merge``: per-second radiance, validity, times and frame paths; no counts."""
    return SimpleNamespace(radiance=merge.radiance / np.float32(merge.reference_time), valid=merge.valid,
                           times=merge.times, paths=merge.paths, units="per_second", wb=None)


def test_levels_recovered_from_the_merge():
    b = make_bracket(_scene(), times=[4.0, 0.5, 0.0625, 0.0078125], noise=False)
    ingest = _as_ingest(b.merge)
    # the longest frame's value is the merged radiance in its units (below the white level where it did not clip)
    lv = longest_level(ingest)
    clean_longest = _scene().max(axis=2) * 4.0
    ok = clean_longest < 0.9
    assert np.allclose(lv[ok], clean_longest[ok], rtol=1e-5)
    used = frames_used(ingest)
    assert np.mean(used == b.merge.frames_used) > 0.999  # ties at the thresholds aside
    assert frames_used(SimpleNamespace(**dict(vars(ingest), units="relative"))) is None  # JPEG: unknown


def test_bracket_checks_name_the_frame():
    scene = _scene()
    over = make_bracket(scene, times=[1e3, 1e2], noise=False)
    with pytest.raises(InputError, match="saturated in every frame") as e:
        check_bracket(_as_ingest(over.merge))
    assert over.merge.paths[0].name in str(e.value) and "shorter exposures" in str(e.value)
    dark = make_bracket(scene * 1e-6, times=[1.0, 0.25], noise=False)
    with pytest.raises(InputError, match="no usable signal") as e:
        check_bracket(_as_ingest(dark.merge))
    assert dark.merge.paths[-1].name in str(e.value) and "longer exposures" in str(e.value)
    check_bracket(_as_ingest(make_bracket(scene, noise=False).merge))  # the default bracket is fine


def test_dim_bracket_warning():
    everywhere = np.ones((64, 96), bool)
    low = 0.1 * DIM_MEDIAN  # the ball's median in the longest frame, far below DIM_MEDIAN; its peak below white
    scene = np.clip(_scene(low), 0, 0.5)
    dim = make_bracket(scene, times=[1.0, 0.25], noise=False)
    w = dim_warning(_as_ingest(dim.merge), everywhere)
    assert w and dim.merge.paths[-1].name in w and "saturates nowhere" in w and "longer exposures" in w
    assert f"{100 * low:.1f}%" in w
    # the same scene with a longest frame 32x longer (median at 0.1 of white, the peak clipping): no warning
    assert dim_warning(_as_ingest(make_bracket(scene, times=[32.0, 1.0, 0.25], noise=False).merge),
                       everywhere) is None
