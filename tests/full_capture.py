"""One small synthetic photographed capture (``objcam synth --full``) per test session, shared by
tests/test_synth_full.py and tests/test_sfm_stage.py: the first test that asks renders it (about 30 s on 2 cores),
the others find it in the session's base temporary folder.

10 DNG views at 320 x 240 (16 spp) on two rings, one target (3-frame bracket, 16 spp, 3 bounces) and one chrome
ball (12 cm, so that it spans ~75 px of the 320 px frame: the probe stage needs 60; 3 frames), noise on.
"""

from __future__ import annotations

import fcntl
from pathlib import Path

SMALL_FULL = dict(n_views=10, width=320, height=240, view_spp=16, target_spp=16, max_depth=3, probe_spp=8,
                  view_distance=0.5, fov_deg=60.0, elevations_deg=[35.0, 55.0], target_distance=0.45,
                  bracket_frames=3, probe_bracket_frames=3, probe_diameter=0.12)


def small_full_capture(tmp_path_factory) -> Path:
    """The shared capture folder (rendered on first use; never modified by the tests: stages run with --work)."""
    from objcam.synth.full import FullSynthParams, synthesize_full

    root = tmp_path_factory.getbasetemp() / "small_full_capture"
    root.mkdir(exist_ok=True)
    cap = root / "capture"
    with open(root / ".lock", "w") as lock:  # one render even if two processes share this base folder
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (cap / "truth" / "truth.json").is_file():
            synthesize_full(cap, FullSynthParams(**SMALL_FULL))
    return cap
