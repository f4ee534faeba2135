"""Parameters of ``objcam design``: which occluders, the shared setup (camera, plane, envmap grid) and how the
comparison is scored. One pydantic model, so the CLI, design.json and the tests agree on names and defaults."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator

BUILTIN = ("bunny", "sphere", "mask")


class DesignParams(BaseModel):
    """Everything that defines one occluder comparison. Lengths in metres, angles in degrees."""

    model_config = ConfigDict(extra="forbid")
    objects: list[str] = Field(list(BUILTIN), description="built-in occluders to compare: bunny, sphere, mask")
    meshes: list[Path] = Field([], description="more occluders: mesh files (PLY, OBJ, STL, OFF), scaled to `size`")
    size: float = Field(0.2, gt=0, le=5, description="largest bounding-box side of every solid occluder, and the "
                                                       "side of the mask, metres")
    mask_height: float = Field(0.15, gt=0, description="height of the coded-aperture mask above the plane, metres")
    mask_cells: int = Field(16, ge=2, le=256, description="mask pattern: cells per side")
    mask_open: float = Field(0.5, gt=0, lt=1, description="mask pattern: fraction of cells that are holes")
    mask_seed: int = Field(0, ge=0, description="seed of the mask's random hole pattern")
    image_size: int = Field(128, ge=8, le=2048, description="camera image width = height, pixels")
    env_height: int = Field(32, ge=4, le=256, description="envmap rows (width 2x)")
    elevation_deg: float = Field(88.0, gt=0, lt=90, description="camera elevation above the plane; near 90 (looking "
                                                                  "down) the view sees shadows cast in every "
                                                                  "direction, so the score is the occluder's, not "
                                                                  "the viewpoint's")
    azimuth_deg: float = Field(-90.0, description="camera azimuth about the origin, from +x towards +y")
    distance: float = Field(3.0, gt=0, description="camera distance from the origin, in units of `size`")
    fov_deg: float = Field(50.0, gt=1, lt=170, description="camera field of view (square image)")
    object_albedo: float = Field(0.6, ge=0, le=1, description="grey albedo of the occluder")
    support_albedo: float = Field(0.5, gt=0, le=1, description="grey albedo of the plane")
    plane_size: float = Field(20.0, gt=0, description="side of the square support plane, metres")
    samples: int = Field(4, ge=1, description="transport: shadow rays per traced (pixel, texel) pair")
    subpixel_samples: int = Field(16, ge=1, description="transport: camera rays per pixel")
    lr: float = Field(1e-6, gt=0, description="ridge weight, relative to the unoccluded plane's mean squared "
                                               "column norm (the same absolute weight for every occluder)")
    threshold: float = Field(0.1, gt=0, lt=1, description="a texel counts as resolved when its uncertainty is "
                                                           "below this fraction of the ridge bound 1/sqrt(lr)")
    rank_tol: float = Field(1e-3, gt=0, lt=1, description="effective rank: singular values above tol x largest")
    zenith_deg: float = Field(60.0, gt=0, lt=90, description="texels above this elevation form the zenith band")
    horizon_deg: float = Field(20.0, gt=0, lt=90, description="upper texels below this elevation form the "
                                                               "horizon band")
    seed: int = Field(0, ge=0, description="transport sampling seed")

    @field_validator("objects")
    @classmethod
    def _known(cls, v: list[str]) -> list[str]:
        bad = [o for o in v if o not in BUILTIN]
        if bad:
            raise ValueError(f"unknown occluder(s) {bad}: choose from {', '.join(BUILTIN)} (meshes go to --mesh)")
        if len(set(v)) != len(v):
            raise ValueError("objects has duplicates")
        return v
