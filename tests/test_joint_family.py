"""The joint-solve family of issue 29, tiny: a dark object of known albedo 0.05 on a support of albedo 0.8 left
unknown, three illuminations (the hard suite's procedural room, window and sun) seen from one camera, rendered by
the hard suite's own Mitsuba scene (bench/hard/scene.py: path-traced, not objcam's A), 2% zero-mean noise,
written per data_layout.md (bench/hard/joint_family.py). The support's albedo comes out within 7% of the truth
with no scale fitted (issue 29's 3% holds on the 128 px bench family, not on this 48 px capture: see below), the
object's pixels of known albedo are predicted within 2% on average, and evaluate scores the albedo as estimated.
The reverse pair (a bright object on a dark support) too.

Why 7% here (session 17, bench/results.md "Issue 29", Session 17): on this 48 px capture the joint solve's own
support albedo is 0.92-0.93 (first solve 0.922, after one refit 0.928; the 128 px bench family's 0.818), and the
final step brings it to 0.847 (+5.9%; blue channel +9.8%). The bounce refit passes the joint estimate to every
support cell, including those no pixel sees (issue 29's fix: they kept the transport's guess, 0.5); before that
fix the too-dark unseen cells offset the too-bright seen ones here (0.799 on this capture, 0.818 with the earlier
render seeds). A second refit leaves it (0.848): its input, the joint solve's albedo, stays at 0.93.
Unexplained: why the joint solve's albedo is biased bright at 48 px and not at 128 px.

Interreflections are forced into A (transport.auto_noise=1e-6): the object's pixels pin the scale, and the light the
bright support throws onto the dark object is 7-26% of it here; without it in A the pinned scale inherits that error
(measured: support 0.684, 14% low; the test keeps it as its broken answer). The transport's `auto` rule does not yet
weigh light on the pinning pixels (bench/results.md, Issue 29)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mitsuba")


@pytest.mark.parametrize("albedo_object, albedo_support", [(0.05, 0.8), (0.8, 0.05)])
def test_support_albedo_of_the_family_without_a_fitted_scale(tmp_path, albedo_object, albedo_support):
    """The dark object on the bright support (the issue's case: its pixels barely hold the scale) and the reverse
    (measured: support 0.0506, +1.2%; object target / prediction 0.980 / 0.997 / 0.999)."""
    from bench.hard.capture import DISTANCE
    from bench.hard.joint_family import lightings, render_family, score, write_family_capture
    from bench.hard.objects import make_object, write_ply
    from bench.hard.scene import look_at_camera
    from objcam.pipeline.engine import Pipeline, parse_overrides

    v, f = make_object("bunny")
    mesh = tmp_path / "bunny.ply"
    write_ply(mesh, v, f)
    camera = look_at_camera(35.0, -90.0, DISTANCE, (0.0, 0.0, 0.02), 48)
    envs = lightings(None, procedural=True)
    images, mcs = render_family(mesh, camera, envs, albedo_object, albedo_support, 128, None, "bunny-el35")
    root = tmp_path / "capture"
    names = write_family_capture(root, v, f, camera, envs, images, albedo_object, albedo_support, False, 0.02,
                                 max(mcs))
    Pipeline(root, root / "objcam", overrides=parse_overrides(["transport.auto_noise=1e-6"]),
             quiet=True).run(until="evaluate")
    rows = [score(root / "objcam", n) for n in names]
    # measured (session 17): dark object support 0.847 (+5.9%), object target / prediction 1.003 / 0.978 / 0.977
    # (mean 0.986); bright object support 0.0511 (+2.1%), 0.999 / 0.999 / 0.999
    sup = rows[0]["support_median"]
    assert abs(sup / albedo_support - 1) < 0.07, sup
    assert abs(np.mean([r["object_ratio"] for r in rows]) - 1) < 0.02, rows
    for n, r in zip(names, rows):
        assert r["scale_ambiguous"] is False and r["albedo_scored_as"] == "as estimated", r
    m = json.loads((root / "objcam" / "evaluate" / "metrics.json").read_text())[names[0]]
    # per channel, as estimated: measured 1.041 / 1.038 / 1.098 for the dark object (blue, the blue sun-sky's
    # channel, the brightest)
    ratio = np.array(m["albedo_mean_ratio"])
    assert m["albedo_scale"] == [1.0, 1.0, 1.0] and abs(ratio.mean() - 1) < 0.07 and np.all(np.abs(ratio - 1) < 0.12)
    info = json.loads((root / "objcam" / "solve" / names[0] / "solve.json").read_text())
    assert info["pinned_scale"] is not None and len(info["pinned_scale"]["factors"]) == 3
    if albedo_object < albedo_support:
        # a test of the test (tests/broken.py): the same photos with the interreflections left out of A (the
        # support's light on the dark object then pins the scale wrong) miss the support's 7% bound (measured
        # 0.684 before session 17, 0.687 after)
        from tests.broken import rerun

        bad = rerun(root, root / "objcam", tmp_path / "direct", ["transport.model=direct"], until="evaluate")
        sup_bad = score(bad, names[0])["support_median"]
        print("interreflections left out of A: support", sup_bad)
        assert not abs(sup_bad / albedo_support - 1) < 0.07, sup_bad
