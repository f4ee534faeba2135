"""The chrome-ball probe as ground truth for ``evaluate`` when a capture has no ``truth/`` (real captures).

:func:`probe_truth` returns the probe stage's envmap for one illumination at the solve resolution, with the texels
it can vouch for. Saturated texels (a sun clipped in every frame: their value is a lower bound) and texels mostly
in the blind spot or the camera's reflection are not valid, so a metric over ``valid`` never scores an estimate
against a number the probe did not measure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from objcam.probe.artifact import coarse_names, read_fine, read_index, read_uint8
from objcam.probe.unwrap import ProbeEnvmap

MAX_SUPERSAMPLE = 4096  # rows of the common grid when the fine height is not a multiple of the requested one


def _downsample(env: np.ndarray, flags: np.ndarray, height: int, min_valid_fraction: float):
    """Area-average a fine probe (env, flags) to ``height`` rows with the unwrap's validity rule; a fine height
    that is not a multiple of ``height`` is first repeated (nearest texel, exact for box texels) to their least
    common multiple."""
    src = env.shape[0]
    if src % height:
        lcm = int(np.lcm(src, height))
        if lcm > MAX_SUPERSAMPLE:
            raise ValueError(f"probe height {src} and requested height {height} have no common grid up to "
                             f"{MAX_SUPERSAMPLE} rows; rerun the probe stage with env_height={height}")
        up = lcm // src
        env = np.repeat(np.repeat(env, up, axis=0), up, axis=1)
        flags = np.repeat(np.repeat(flags, up, axis=0), up, axis=1)
    probe = ProbeEnvmap(env, flags, np.ones(flags.shape, np.float32), "perspective")
    e, valid, _ = probe.downsample(height, min_valid_fraction)
    return e, valid


def probe_truth(probe_stage_dir: Path, illumination: str, height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(envmap (height, 2 height, 3) float64 linear radiance in the probe image's units, valid (height,
    2 height) bool) of the probe photographed under ``illumination`` (a target's illumination name, see
    capture.toml), or None when the probe stage's folder has no such probe.

    Uses the stage's ``envmap_gt_<height>.exr`` / ``valid_<height>.png`` when it wrote that resolution, else
    area-averages the full-resolution ``envmap_gt.exr`` with its ``flags.png`` (same rule). When several probes
    share the illumination, the one whose valid texels cover the most solid angle wins.
    """
    stage = Path(probe_stage_dir)
    if not stage.is_dir():
        return None
    matches = [(name, e) for name, e in read_index(stage).items() if e.get("illumination", name) == illumination]
    if not matches:
        return None
    name, entry = max(matches, key=lambda m: (float(m[1].get("valid_fraction_solid_angle", 0.0)), m[0]))
    folder = stage / entry.get("folder", name)
    e_name, v_name, _ = coarse_names(height)
    if (folder / e_name).is_file() and (folder / v_name).is_file():
        from objcam.envmap import read_latlong

        env = read_latlong(folder / e_name)[..., :3].astype(np.float64)
        valid = read_uint8(folder / v_name) > 127
        return env, valid
    env, flags, rec = read_fine(folder)
    e, valid = _downsample(env, flags, height, float(rec.get("min_valid_fraction", 0.5)))
    return e.astype(np.float64), valid
