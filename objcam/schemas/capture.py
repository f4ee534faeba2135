"""``capture.toml``: the manifest of a capture (see data_layout.md for the whole contract).

Two flavours share one schema. A known-geometry capture names the object mesh and gives every target as a linear
HDR image with its camera file. A photographed capture gives raw (or TIFF/JPEG) photos: a ``[views]`` folder for
structure from motion, each target as a folder holding one image or an exposure bracket, the printed ``[board]``
(or a known object size, ``[scale]``) for the metric world frame, optional chrome-ball ``[[probes]]``; the
``ingest``, ``sfm``, ``geometry``, ``texture`` and ``probe`` stages turn those into what the known-geometry
flavour states directly. ``scene.object`` may then be omitted (the shape is reconstructed from the views).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from objcam.errors import InputError
from objcam.sfm.board import BoardSpec

RGB = tuple[float, float, float]


class TextureAlbedo(BaseModel):
    """An albedo texture: a linear image (EXR) over the mesh's UVs, or over a square of ``extent`` metres centred
    on the origin for the support plane (clamped outside it)."""

    model_config = ConfigDict(extra="forbid")
    texture: str
    extent: float | None = Field(default=None, gt=0)


class UniformAlbedo(BaseModel):
    """``"uniform"``: the surface has one albedo (per colour) of unknown value, e.g. a 3D print in one filament or
    plain paper; the solve estimates that one value instead of one per pixel."""

    model_config = ConfigDict(extra="forbid")
    uniform: Literal[True] = True


#: the keyword of :class:`UniformAlbedo` in capture.toml (``object = "uniform"``)
UNIFORM = "uniform"

AlbedoSpec = Union[float, RGB, TextureAlbedo, UniformAlbedo]


class SceneSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    object: str | None = Field(default=None, min_length=1, description="object mesh (PLY/OBJ/STL), world metres, resting on "
                               "z = 0; for a photographed capture the known shape (e.g. the 3D-printed model, "
                               "any pose and unit: the geometry stage registers it); omitted: reconstructed "
                               "from the views")
    support: str = Field(default="plane", min_length=1, description="'plane' for z = 0, or a support mesh file")
    plane_size: float = Field(default=20.0, gt=0, le=1e4, allow_inf_nan=False,
                              description="side of the square support plane, metres (the scene stage also asks "
                              "that it cover the object's footprint)")


class AlbedoSection(BaseModel):
    model_config = ConfigDict(extra="forbid")
    object: AlbedoSpec | None = None
    support: AlbedoSpec | None = None

    @field_validator("object", "support", mode="before")
    @classmethod
    def _parse(cls, v):
        if isinstance(v, bool) or (isinstance(v, list) and any(isinstance(x, bool) for x in v)):
            raise ValueError("albedo is a number in [0, 1] (or [r, g, b], or a texture), not true/false")
        if isinstance(v, str) and v.strip().lower() == UNIFORM:
            return UniformAlbedo()
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
        if any(not (0.0 <= x <= 1.0) for x in vals):  # NaN fails this too
            raise ValueError("albedo values must lie in [0, 1]")
        return v


def _file_name(v: str) -> str:
    """A name that becomes a folder under objcam/: never "." or ".." (which would write outside its folder)."""
    if set(v) == {"."}:
        raise ValueError(f"{v!r} is not a usable name (it names a folder, not a file)")
    return v


class TargetSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", max_length=100)
    image: str | None = Field(default=None, min_length=1, description="linear HDR image (EXR)")
    folder: str | None = Field(default=None, min_length=1, description="folder holding one photo or an exposure bracket "
                               "(raw, 16-bit TIFF, JPEG or EXR), merged to linear HDR by the ingest stage")
    camera: str | None = Field(default=None, min_length=1, description="camera JSON: width, height, fx, fy, cx, cy, "
                               "world_from_camera; omitted in a photographed capture (the sfm stage poses it)")
    illumination: str | None = Field(default=None, description="targets with the same illumination name show "
                                     "the same envmap from different cameras (default: the target's own name)")
    mask: str | None = Field(default=None, min_length=1, description="optional image, nonzero = usable pixel")
    radiometry: Literal["absolute", "relative"] | None = Field(
        default=None, description="'absolute': the image is radiance in the envmap's units (synthetic, calibrated); "
        "'relative': radiance times an unknown camera gain, so the envmap is right up to one factor and evaluate "
        "compares up to it. Default: relative for photos (folder), absolute for an image")
    saturation: float | None = Field(default=None, gt=0, allow_inf_nan=False,
                                     description="pixels >= this in any channel are excluded")
    noise_sigma: float | None = Field(default=None, ge=0, allow_inf_nan=False,
                                      description="relative noise of the image, if known (used by transport auto)")
    encoding: Literal["linear", "srgb"] | None = Field(
        default=None, description="how to linearise an integer (8- or 16-bit) image: 'srgb' (the sRGB curve) or "
        "'linear' (code values are linear); without it such an image is refused (a float EXR needs none)")

    _name = field_validator("name")(_file_name)

    @model_validator(mode="after")
    def _source(self):
        if (self.image is None) == (self.folder is None):
            raise ValueError(f"target {self.name!r}: give exactly one of image (a linear EXR) or folder (photos)")
        return self

    @property
    def illumination_name(self) -> str:
        return self.illumination or self.name


class CameraFacts(BaseModel):
    """``[camera]``: what the photographer knows about the camera; everything else is read from the files."""

    model_config = ConfigDict(extra="forbid")
    white_balance: Union[Literal["camera", "daylight", "none"], RGB] = Field(
        "camera", description="raw white balance: the camera's as-shot multipliers, daylight, none (raw camera "
        "RGB) or explicit [r, g, b] multipliers")
    demosaic: Literal["superpixel", "bilinear"] = Field("superpixel", description="raw demosaicing (superpixel "
                                                        "halves the size, no interpolation)")
    exposure_times: dict[str, float] = Field(default_factory=dict, description="exposure time override, seconds, "
                                             "by file name, for files without EXIF")
    exposure_time: float | None = Field(None, gt=0, allow_inf_nan=False, description="seconds, for every photo "
                                        "without an EXIF exposure time (a folder of JPEGs shot at one setting); "
                                        "exposure_times and EXIF take precedence")
    distortion: list[float] | None = Field(None, description="OpenCV distortion k1 k2 p1 p2 [k3], if known")
    focal_px: float | None = Field(None, gt=0, description="focal length in pixels of the decoded photo (after "
                                   "demosaicing), principal point at the centre: the K the distortion was "
                                   "calibrated with (needed with distortion)")


class ViewsSpec(BaseModel):
    """``[views]``: the photos for structure from motion (the object on the board, from all around)."""

    model_config = ConfigDict(extra="forbid")
    folder: str = Field("views", description="folder of photos (raw, TIFF, JPEG or PNG)")
    max_size: int = Field(1600, ge=200, le=16384, description="longest side of the copies SfM sees, pixels")


class ScaleSpec(BaseModel):
    """``[scale]``: the metric reference when there is no board: the known height of the object."""

    model_config = ConfigDict(extra="forbid")
    object_height: float = Field(gt=0, description="object height above the support, metres")


class ProbeSpec(BaseModel):
    """``[[probes]]``: a chrome ball photographed (one image or a bracket) at the object's place, per illumination."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", max_length=100)
    _name = field_validator("name")(_file_name)
    folder: str = Field(description="folder holding the ball photo or its exposure bracket")
    illumination: str | None = Field(None, description="the illumination (target name) it is ground truth for "
                                     "(default: its own name)")
    diameter: float = Field(gt=0, description="ball diameter, metres")
    centre: tuple[float, float, float] | None = Field(None, description="ball centre in world metres; default: it "
                                                      "rests on z = 0 where the photo shows it")
    camera: str | None = Field(None, description="camera JSON of the photo; default: posed by the sfm stage")
    reflectance: float | None = Field(None, gt=0, le=1, description="chrome reflectance calibration factor "
                                      "(default: a measured typical value)")

    @property
    def illumination_name(self) -> str:
        return self.illumination or self.name


class CaptureManifest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene: SceneSpec = SceneSpec()
    albedo: AlbedoSection = AlbedoSection()
    targets: list[TargetSpec] = Field(min_length=1)
    camera: CameraFacts = CameraFacts()
    views: ViewsSpec | None = None
    board: BoardSpec | None = None
    scale: ScaleSpec | None = None
    probes: list[ProbeSpec] = Field(default_factory=list)
    # [params.<stage>]: settings kept with the capture (objcam.pipeline.params checks the stage and names)
    params: dict[str, dict[str, Any]] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _flavour(self):
        if self.views is None:
            if self.scene.object is None:
                raise ValueError("scene.object is required when the capture has no [views] to reconstruct it from")
            posed = [t.name for t in self.targets if t.camera is None]
            if posed:
                raise ValueError(f"target(s) {', '.join(posed)} have no camera and there are no [views] for "
                                 "structure from motion to pose them")
            unposed = [p.name for p in self.probes if p.camera is None]
            if unposed:
                raise ValueError(f"probe(s) {', '.join(unposed)} have no camera and there are no [views]")
        elif self.board is None and self.scale is None:
            raise ValueError("a capture with [views] needs a metric reference: a [board] section (the printed "
                             "ChArUco board) or [scale] object_height")
        names = [p.name for p in self.probes]
        if len(set(names)) != len(names):
            raise ValueError("probe names must be unique")
        return self

    @property
    def photographed(self) -> bool:
        """True when some stage must work from photos (views, photo targets or probes)."""
        return self.views is not None or bool(self.probes) or any(t.folder for t in self.targets)

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


def try_load(capture_dir: str | Path) -> CaptureManifest | None:
    """The manifest, or None when it is missing or invalid (the scene stage reports why, in one line).
    Stages' ``applies`` tests use this: they must never fail."""
    try:
        return CaptureManifest.load(capture_dir)
    except InputError:
        return None
