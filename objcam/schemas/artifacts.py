"""Artifacts passed between stages: what the ``scene`` stage writes and every later stage reads.

Scene artifact folder (``objcam/scene/``):
    scene.json          SceneDescription (mesh and texture paths relative to the folder)
    object.npz          MeshData of the object, world metres
    support.npz         MeshData of the support (the plane z = 0 is a mesh too)
    albedo_*.exr        albedo textures, when the capture gives textures
    targets.json        list of TargetRecord
    targets/<name>/image.exr   linear RGB float32 (H, W, 3), as read from the capture
    targets/<name>/valid.png   uint8 (H, W), 255 = usable pixel (finite, unsaturated, inside the user mask)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from objcam.camera import Camera
from objcam.scene import SceneDescription


class TargetRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    camera: Camera
    image: str  # relative to the scene artifact folder
    valid: str  # relative to the scene artifact folder
    illumination: str = ""  # targets sharing it show one envmap from several cameras (default: the target's name)
    saturation: float | None = None
    noise_sigma: float | None = None
    radiometry: str = "absolute"  # "relative": radiance x an unknown camera gain (photos decoded by ingest)
    n_valid: int
    n_pixels: int

    def load_image(self, folder: Path) -> np.ndarray:
        """(H, W, 3) float32 linear radiance."""
        from objcam.image_io import read_exr

        img = read_exr(folder / self.image)
        return img[..., :3] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)

    def load_valid(self, folder: Path) -> np.ndarray:
        """(H, W) bool, True where the pixel may be fitted."""
        import cv2

        return cv2.imread(str(folder / self.valid), cv2.IMREAD_UNCHANGED) > 127


class SceneArtifact(BaseModel):
    """Convenience reader of a finished scene artifact folder."""

    model_config = ConfigDict(arbitrary_types_allowed=True)
    folder: Path
    description: SceneDescription
    targets: list[TargetRecord]

    @classmethod
    def load(cls, folder: str | Path) -> "SceneArtifact":
        folder = Path(folder)
        desc = SceneDescription.model_validate_json((folder / "scene.json").read_text())
        targets = [TargetRecord.model_validate(t) for t in json.loads((folder / "targets.json").read_text())]
        return cls(folder=folder, description=desc, targets=targets)

    def target(self, name: str) -> TargetRecord:
        for t in self.targets:
            if t.name == name:
                return t
        raise KeyError(name)
