"""Stage ``geometry``: object and support meshes in world metres from the photos (issue 4).

Applies when the capture has ``[views]`` (so sfm has posed them). Known shape (``scene.object``): registered to
the reconstruction; otherwise reconstructed from silhouettes. Writes:
    object.npz, support.npz        MeshData (objcam.scene), world metres, object resting on z = 0
    geometry.json                  plane fit residual (mm), registration residual (mm) or reconstruction stats
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict

from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import try_load

NAME = "geometry"
DEPS: tuple[str, ...] = ("ingest", "sfm")
VERSION = "1"
APPLIES_WHEN = "the capture has [views]"


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and m.views is not None


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    raise NotImplementedError("geometry: being built (issue 4)")
