"""Stage ``texture``: UVs and a first linear albedo of the support and the object from the views (issue 4).

Applies with ``geometry``. Writes:
    object.npz, support.npz        the geometry stage's meshes with xatlas UVs (MeshData.uv)
    albedo_object.exr, albedo_support.exr   linear albedo textures over those UVs (RGB float32)
    confidence_*.exr, counts_*.exr per-texel confidence in [0, 1] and sample counts
    texture.json                   what was baked, how many samples were rejected as shadowed/occluded
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict

from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import try_load

NAME = "texture"
DEPS: tuple[str, ...] = ("ingest", "sfm", "geometry")
VERSION = "1"
APPLIES_WHEN = "the capture has [views]"


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and m.views is not None


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    raise NotImplementedError("texture: being built (issue 4)")
