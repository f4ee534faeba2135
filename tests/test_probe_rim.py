"""The chrome ball's rim model (objcam.probe.rim) and the fit steps around it (objcam.probe.fit: the contact arc
check), against rendered balls with known centres.

Only the pixels within 6 px of the silhouette are rendered (``render_probe(band_px=...)``): all the rim fit and
the edge fit read, at a fraction of a full render's cost. The ball floats at z = radius (no support) unless a
plane is rendered.
"""

from __future__ import annotations

import numpy as np
import pytest

from objcam.probe import fit as F
from objcam.probe.rim import _coverage, refine_rim
from objcam.synth.probe import make_bracket, render_probe

R = 0.025  # 5 cm ball


def _pixel_of(cam) -> float:
    """Metres per image pixel at the ball's distance (the centre's projection moves ~1 px per this)."""
    return R / (cam.fx * np.tan(np.arcsin(R / np.linalg.norm(np.array([0.0, 0.0, R]) - cam.centre))))


@pytest.mark.parametrize("p", [0.0, 0.5])
def test_coverage_matches_supersampling(p):
    """The closed-form pixel mean of max(depth, 0)^p across a straight edge equals a 256 x 256 supersampled box."""
    rng = np.random.default_rng(0)
    x = (np.arange(256) + 0.5) / 256 - 0.5
    xx, yy = np.meshgrid(x, x)
    for _ in range(20):
        ang = rng.uniform(0, 2 * np.pi)
        e = rng.uniform(-1.2, 1.2)
        n = np.array([np.cos(ang), np.sin(ang)])
        t = e + xx * n[0] + yy * n[1]  # depth beyond the edge of each sub-sample
        want = np.mean(np.where(t > 0, np.maximum(t, 0) ** p, 0.0))
        got = _coverage(np.array([e]), np.array([max(abs(n[0]), 1e-3)]), np.array([max(abs(n[1]), 1e-3)]), p)[0]
        assert got == pytest.approx(want, abs=3e-3)


@pytest.fixture(scope="module")
def floating():
    """Courtyard, 1000 px image, ball 700 px across, 8 spp: only the rim band rendered, then bracketed."""
    r = render_probe("courtyard", radius=R, size=1000, ball_px=700.0, spp=8, seed=1, elevation_deg=25.0,
                     azimuth_deg=30.0, offset_px=(60.0, -40.0), band_px=6.0)
    return r, make_bracket(r.clean, seed=2)


def test_rim_model_beats_the_edge_fit(floating):
    r, b = floating
    cam = r.camera
    start = r.centre + np.array([0.5, -0.4, 0.0]) * _pixel_of(cam)  # ~0.6 px off
    logc = F.log_rgb(b.hdr)
    edge = F._refine(logc, cam, R, start, "plane", "ball", F.WINDOWS, 1.0)  # contact arc skipped
    e_edge = np.linalg.norm(edge.centre_world - r.centre)
    # the floating ball has no contact shadow: its contact arc's edges agree with the rest
    assert F._contact_arc_agrees(logc, cam, edge.centre_world, R, 1.0)
    rim = refine_rim(b.hdr, b.merge.valid, cam, R, edge.centre_world, plane=True, skip_contact=0.0)
    e_rim = np.linalg.norm(rim.centre - r.centre)
    assert rim.centre[2] == R and rim.coverage == 1.0
    # measured 0.007 mm against 0.045 mm (the edge points sit 0.3-0.5 px inside the upper rim); 1 px = 0.07 mm
    assert e_rim < 0.015e-3 and e_rim < 0.4 * e_edge, (e_rim, e_edge)


def test_contact_arc_without_edges_is_skipped(floating):
    """The contact arc is fitted only when its edges agree with the rest: blank it (a deep contact shadow, the
    ball reflecting it: no edge left) and the check refuses it; the fit then leaves that arc out."""
    r, b = floating
    cam = r.camera
    img = b.hdr.copy()
    vv, uu = np.nonzero(img.max(axis=2) > 0)  # the rendered band around the silhouette
    _, d = cam.rays(uu.astype(float), vv.astype(float))
    t = -cam.centre[2] / d[:, 2]
    q = cam.centre + t[:, None] * d
    shadow = (t > 0) & (np.hypot(q[:, 0] - r.centre[0], q[:, 1] - r.centre[1]) < 1.2 * R)
    rng = np.random.default_rng(0)
    img[vv[shadow], uu[shadow]] = 0.01 * np.median(img[img > 0]) * (1 + 0.05 * rng.standard_normal((shadow.sum(), 3)))
    logc = F.log_rgb(img)
    edge = F._refine(logc, cam, R, r.centre, "plane", "ball", F.WINDOWS, 1.0)
    assert F._contact_arc_agrees(F.log_rgb(b.hdr), cam, edge.centre_world, R, 1.0)  # the untouched image
    assert not F._contact_arc_agrees(logc, cam, edge.centre_world, R, 1.0)
