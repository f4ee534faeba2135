"""Pinhole cameras in the OpenCV convention (x right, y down, z forward) with world-frame poses.

Pixel (u, v) = (column, row) has its centre at integer coordinates, as in OpenCV: the ray through pixel centre
(u, v) has camera-frame direction ((u - cx) / fx, (v - cy) / fy, 1).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from objcam.errors import InputError


class Camera(BaseModel):
    """Intrinsics in pixels and the 4x4 ``world_from_camera`` rigid transform (metres)."""

    # extra="forbid": a misspelt key ("fx " or "focal") is an error, as in capture.toml, not silently ignored
    model_config = ConfigDict(frozen=True, extra="forbid")

    width: int = Field(gt=0, le=1 << 16)
    height: int = Field(gt=0, le=1 << 16)
    fx: float = Field(gt=0, allow_inf_nan=False)
    fy: float = Field(gt=0, allow_inf_nan=False)
    cx: float = Field(allow_inf_nan=False)
    cy: float = Field(allow_inf_nan=False)
    world_from_camera: list[list[float]]

    @field_validator("world_from_camera")
    @classmethod
    def _rigid(cls, m: list[list[float]]) -> list[list[float]]:
        a = np.asarray(m, dtype=float)
        if a.shape != (4, 4):
            raise ValueError("world_from_camera must be a 4x4 matrix")
        if not np.all(np.isfinite(a)):
            raise ValueError("world_from_camera holds NaN or infinite values")
        r = a[:3, :3]
        with np.errstate(all="ignore"):  # finite but huge entries overflow here: they fail the test, quietly
            rigid = np.allclose(r.T @ r, np.eye(3), atol=1e-4) and np.linalg.det(r) > 0
        if not rigid:
            raise ValueError("world_from_camera's rotation is not orthonormal with determinant +1")
        if not np.allclose(a[3], [0, 0, 0, 1]):
            raise ValueError("world_from_camera's last row must be [0, 0, 0, 1]")
        return m

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) world_from_camera."""
        return np.asarray(self.world_from_camera, dtype=np.float64)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in world metres."""
        return self.matrix[:3, 3].copy()

    def rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-frame rays through continuous pixel coordinates ``u`` (column) and ``v`` (row).

        Returns origins (..., 3) and unit directions (..., 3).
        """
        d_cam = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u, dtype=float)], -1)
        d = d_cam @ self.matrix[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(self.centre, d.shape).copy()
        return o, d

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) of world points (..., 3) (no visibility test)."""
        cam_from_world = np.linalg.inv(self.matrix)
        p = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        return np.stack([self.fx * p[..., 0] / p[..., 2] + self.cx, self.fy * p[..., 1] / p[..., 2] + self.cy], -1)

    @classmethod
    def load(cls, path: str | Path) -> "Camera":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise InputError("camera file not found", path, "write a JSON with width, height, fx, fy, cx, cy, "
                             "world_from_camera (see data_layout.md)") from None
        except json.JSONDecodeError as e:
            raise InputError(f"camera file is not valid JSON ({e.msg}, line {e.lineno})", path) from None
        except UnicodeDecodeError:
            raise InputError("camera file is not a text (JSON) file", path) from None
        except IsADirectoryError:
            raise InputError("camera file is a folder", path, "give the JSON file") from None
        if not isinstance(data, dict):
            raise InputError("camera file is not a JSON object", path, "see the camera format in data_layout.md")
        try:
            return cls.model_validate(data)
        except Exception as e:  # pydantic.ValidationError: condense to one line
            msg = "; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())  # type: ignore[attr-defined]
            raise InputError(f"invalid camera ({msg})", path, "see the camera format in data_layout.md") from None

    def save(self, path: str | Path) -> None:
        from objcam.image_io import atomic_write_text

        atomic_write_text(path, json.dumps(self.model_dump(), indent=2))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """4x4 world_from_camera (OpenCV axes) for a camera at ``eye`` looking at ``target``."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-8:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m
