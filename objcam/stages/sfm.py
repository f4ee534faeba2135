"""Stage ``sfm``: world-frame, metric cameras for every photo (issue 3).

Applies when the capture has ``[views]``. Runs pycolmap over ingest's view copies together with the targets' and
probes' SfM copies, puts the model in the world frame (board in z = 0, metres; or ``[scale]``), writes:
    sparse/0/                      COLMAP binary model, world frame, metres (readable by COLMAP's tools)
    cameras/views/<stem>.json      objcam Camera JSON matching ingest/views/<stem>.exr's size
    cameras/targets/<name>.json    matching ingest/targets/<name>/image.exr's size
    cameras/probes/<name>.json     matching ingest/probes/<name>/image.exr's size
    points.npz                     xyz (P,3) float64 world metres, rgb (P,3) uint8, error (P,) px, track (P,) int
    report.json                    registered/total, reprojection error, scale/plane residuals, graded checks
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict

from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import try_load

NAME = "sfm"
DEPS: tuple[str, ...] = ("ingest",)
VERSION = "1"
APPLIES_WHEN = "the capture has [views]"


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and m.views is not None


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    raise NotImplementedError("sfm: being built (issue 3)")
