"""``capture.toml``: the manifest of a known-geometry capture (see data_layout.md for the whole contract)."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from objcam.errors import InputError

RGB = tuple[float, float, float]


class TextureAlbedo(BaseModel):
    """An albedo texture: a linear image (EXR) over the mesh's UVs, or over a square of ``extent`` metres centred
    on the origin for the support plane (clamped outside it)."""

    model_config = ConfigDict(extra="forbid")
    texture: str
    extent: float | None = Field(default=None, gt=0)


AlbedoSpec = Union[float, RGB, TextureAlbedo]


class SceneSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    object: str = Field(description="object mesh (PLY/OBJ/STL), world metres, resting on z = 0")
    support: str = Field(default="plane", description="'plane' for z = 0, or a support mesh file")
    plane_size: float = Field(default=20.0, gt=0, description="side of the square support plane, metres")


class AlbedoSection(BaseModel):
    model_config = ConfigDict(extra="forbid")
    object: AlbedoSpec | None = None
    support: AlbedoSpec | None = None

    @field_validator("object", "support", mode="before")
    @classmethod
    def _parse(cls, v):
        if isinstance(v, str):
            return TextureAlbedo(texture=v)
        if isinstance(v, list):
            if len(v) != 3:
                raise ValueError("an RGB albedo needs 3 values")
            return tuple(float(x) for x in v)
        return v

    @field_validator("object", "support")
    @classmethod
    def _range(cls, v):
        vals = [v] if isinstance(v, float) else list(v) if isinstance(v, tuple) else []
        if any(not (0.0 <= x <= 1.0) for x in vals):
            raise ValueError("albedo values must lie in [0, 1]")
        return v


class TargetSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    image: str = Field(description="linear HDR image (EXR)")
    camera: str = Field(description="camera JSON: width, height, fx, fy, cx, cy, world_from_camera")
    mask: str | None = Field(default=None, description="optional image, nonzero = usable pixel")
    saturation: float | None = Field(default=None, gt=0, description="pixels >= this in any channel are excluded")
    noise_sigma: float | None = Field(default=None, ge=0,
                                      description="relative noise of the image, if known (used by transport auto)")


class CaptureManifest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene: SceneSpec
    albedo: AlbedoSection = AlbedoSection()
    targets: list[TargetSpec] = Field(min_length=1)

    @field_validator("targets")
    @classmethod
    def _unique(cls, v: list[TargetSpec]):
        names = [t.name for t in v]
        if len(set(names)) != len(names):
            raise ValueError("target names must be unique")
        return v

    @classmethod
    def load(cls, capture_dir: str | Path) -> "CaptureManifest":
        path = Path(capture_dir) / "capture.toml"
        if not Path(capture_dir).is_dir():
            raise InputError("capture folder not found", capture_dir, "give the folder that holds capture.toml")
        if not path.is_file():
            raise InputError("capture.toml not found", path,
                             "write one (see data_layout.md) or make a synthetic capture with `objcam synth`")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"capture.toml is not valid TOML ({e})", path) from None
        except UnicodeDecodeError:
            raise InputError("capture.toml is not a text file", path) from None
        try:
            return cls.model_validate(data)
        except ValidationError as e:
            msg = "; ".join(f"{'.'.join(map(str, err['loc'])) or '(top)'}: {err['msg']}" for err in e.errors()[:4])
            raise InputError(f"invalid capture.toml ({msg})", path, "see the manifest format in data_layout.md") from None


def albedo_is_known(spec: AlbedoSpec | None) -> bool:
    return spec is not None


SupportKind = Literal["plane", "mesh"]
