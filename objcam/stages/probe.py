"""Stage ``probe``: chrome-ball HDR ground truth (issue 5).

Applies when the capture lists ``[[probes]]``. Reads ingest's merged probe images and the probe cameras (from the
manifest or sfm/cameras/probes/). Writes per probe ``<name>/``:
    envmap_gt.exr           full-resolution lat-long envmap (objcam convention, world frame), linear RGB
    envmap_gt_<H>.exr       area-averaged to the solve resolution (H x 2H; H = the transport's env_height)
    valid.png, valid_<H>.png   texels the ball shows (not the camera's reflection, not the blind spot)
    probe.json              ball centre and radius fit, residuals, saturated-source flags, reflectance used
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict

from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import try_load

NAME = "probe"
DEPS: tuple[str, ...] = ("ingest",)
OPTIONAL_DEPS: tuple[str, ...] = ("sfm",)
VERSION = "1"
APPLIES_WHEN = "the capture lists [[probes]]"


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and bool(m.probes)


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    raise NotImplementedError("probe: being built (issue 5)")
