"""Deliberately broken answers for the accuracy tests (issue 28): a test of the test.

Every accuracy bound in the suite is run once more on a broken answer to the same scene, which must FAIL it: a
bound that a constant envmap, a solve drowned in its prior (``solve.ls=1e6``), one shadow ray per pixel or a
rotated envmap also passes checks nothing. The broken answers reuse the test's own run: the constant and rotated
maps are made from its truth and its estimate, and a broken setting reruns only the stages it changes in a copy
of the test's artifact folder (the capture is never touched).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from objcam.baselines import constant_map


def truth_constant(truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, 2H, 3) the truth's solid-angle mean per channel on the solved texels (0 elsewhere): a flat sky of the
    right brightness, the best an answer that learnt nothing from the shadows can do."""
    return constant_map(truth, mask) * np.asarray(mask, bool)[..., None]


def rotated(env: np.ndarray, mask: np.ndarray, degrees: float) -> np.ndarray:
    """(H, 2H, 3) ``env`` turned about +z by ``degrees`` (whole columns), kept on ``mask``: the right light in the
    wrong place."""
    cols = int(round(degrees / 360.0 * env.shape[1]))
    return np.roll(env, cols, axis=1) * np.asarray(mask, bool)[..., None]


def rerun(capture: Path, work: Path, dest: Path, sets: list[str], until: str = "solve") -> Path:
    """A copy of the artifact folder ``work`` at ``dest``, run to ``until`` with ``--set`` ``sets`` (only the
    stages the settings change rerun). Returns ``dest``."""
    from objcam.pipeline.cli import main

    if not dest.exists():
        shutil.copytree(work, dest)
    args = ["run", str(capture), "--quiet", "--work", str(dest), "--until", until]
    for s in sets:
        args += ["--set", s]
    assert main(args) == 0, sets
    return dest


def solve_info(work: Path, target: str = "t0") -> dict:
    return json.loads((work / "solve" / target / "solve.json").read_text())


def read_envmap(work: Path, target: str = "t0") -> tuple[np.ndarray, np.ndarray]:
    """(envmap (H, 2H, 3) float64, solved-texel mask (H, 2H) bool) of a solve."""
    import cv2

    from objcam.image_io import read_exr

    d = work / "solve" / target
    env = read_exr(d / "envmap.exr")[..., :3].astype(np.float64)
    return env, cv2.imread(str(d / "envmap_mask.png"), cv2.IMREAD_UNCHANGED) > 127
