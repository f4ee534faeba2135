"""Stage ``ingest``: photos -> linear images (issue 3).

Applies when the capture has photos: a ``[views]`` folder, a target given as a ``folder`` or any ``[[probes]]``.

Artifact folder (``objcam/ingest/``), the contract the sfm, geometry, texture, probe and scene stages read:
    views.json                 list of {name (file stem), source (capture-relative path), width, height,
                               scale (copy size / photo size), exposure {time_s, iso, f_number}, white_balance}
    views/<stem>.png           8-bit sRGB copy for SfM (longest side <= views.max_size), undistorted if
                               [camera] distortion is given
    views/<stem>.exr           linear RGB float32 at the same size (raw-linear camera RGB, exposure-normalised
                               to radiance x 1 s), for texture baking
    targets/<name>/image.exr   linear HDR RGB float32 (merged bracket, exposure-normalised)
    targets/<name>/valid.png   255 = usable (not saturated in every frame, finite)
    targets/<name>/merge.json  frames, exposure times, weights used, saturated fraction, reader used
    targets/<name>/sfm.png     8-bit tonemapped copy of the target at the views' scale, for SfM
    probes/<name>/...          the same four files for every chrome-ball bracket
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict

from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import try_load

NAME = "ingest"
DEPS: tuple[str, ...] = ()
VERSION = "1"
APPLIES_WHEN = "the capture has photos ([views], a target folder or [[probes]])"


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and m.photographed


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    raise NotImplementedError("ingest: being built (issue 3)")
