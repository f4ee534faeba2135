"""The suite's three objects, in world metres resting on z = 0, centred on the z axis: the bundled bunny, a torus
lying flat (a hole through which the sky is seen) and a chair-like frame (thin legs and rails, a slab seat).

The torus and the frame are generated here (no licence needed); the bunny is objcam/assets/bunny.ply (Stanford
Bunny, credit the Stanford Computer Graphics Laboratory; see objcam/assets/LICENSES.md), read with a small PLY
reader of its own so that nothing of objcam's scene code is involved.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

OBJECTS = ("bunny", "torus", "frame")
SIZE = 0.08  # metres: every object's largest horizontal extent or height
BUNNY = Path(__file__).resolve().parents[2] / "objcam" / "assets" / "bunny.ply"


def read_binary_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of a binary little-endian PLY with float x y z vertices and
    uchar-counted int triangle lists (the bundled bunny's layout)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    nv = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    nf = int(next(line.split()[2] for line in header if line.startswith("element face")))
    v = np.frombuffer(data, np.float32, nv * 3, end).reshape(nv, 3).astype(np.float64)
    f = np.frombuffer(data, np.dtype([("n", "u1"), ("i", "<i4", 3)]), nf, end + nv * 12)
    if not np.all(f["n"] == 3):
        raise ValueError(f"{path}: faces are not all triangles")
    return v, f["i"].astype(np.int64)


def write_ply(path: Path, v: np.ndarray, f: np.ndarray) -> None:
    """Binary little-endian PLY (float32 vertices, uchar-int triangles)."""
    head = (f"ply\nformat binary_little_endian 1.0\ncomment objcam bench/hard\nelement vertex {len(v)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    faces = np.zeros(len(f), np.dtype([("n", "u1"), ("i", "<i4", 3)]))
    faces["n"], faces["i"] = 3, f
    path.write_bytes(head + np.asarray(v, "<f4").tobytes() + faces.tobytes())


def torus(major: float = 0.03, minor: float = 0.01, n: int = 64, m: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A torus lying on z = 0 (axis +z): ring radius ``major``, tube radius ``minor``."""
    u = 2 * np.pi * np.arange(n) / n
    w = 2 * np.pi * np.arange(m) / m
    uu, ww = np.meshgrid(u, w, indexing="ij")
    r = major + minor * np.cos(ww)
    v = np.stack([r * np.cos(uu), r * np.sin(uu), minor + minor * np.sin(ww)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a, b = i * m + j, ((i + 1) % n) * m + j
    c, d = ((i + 1) % n) * m + (j + 1) % m, i * m + (j + 1) % m
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f


def box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box, 12 outward-facing triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    return v, f


def frame(size: float = SIZE, leg: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """A chair-like frame: four square legs of side ``leg``, a thin seat slab at 0.55 size, a back of two posts and
    two rails; ``size`` tall and 0.75 size wide."""
    half = 0.375 * size
    seat = 0.55 * size
    parts = [box((sx * half - leg / 2 * (1 + sx), sy * half - leg / 2 * (1 + sy), 0),
                 (sx * half + leg / 2 * (1 - sx), sy * half + leg / 2 * (1 - sy), seat))
             for sx in (-1, 1) for sy in (-1, 1)]
    parts.append(box((-half, -half, seat), (half, half, seat + 0.004)))
    for sx in (-1, 1):  # back posts above the seat at +y
        parts.append(box((sx * half - leg / 2 * (1 + sx), half - leg, seat), (sx * half + leg / 2 * (1 - sx), half,
                                                                               size)))
    for z in (0.78 * size, size - 0.004):  # back rails
        parts.append(box((-half, half - leg, z), (half, half, z + 0.004)))
    parts.append(box((-half, -half + leg, 0.2 * size), (-half + leg, half - leg, 0.2 * size + 0.004)))  # a rung
    vs, fs, k = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + k)
        k += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def make_object(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) metres, faces (F, 3)) of object ``name``, resting on z = 0."""
    if name == "bunny":
        v, f = read_binary_ply(BUNNY)
        v = v - [0.5 * (v[:, 0].min() + v[:, 0].max()), 0.5 * (v[:, 1].min() + v[:, 1].max()), v[:, 2].min()]
        v = v * (SIZE / np.ptp(v, axis=0).max())
    elif name == "torus":
        v, f = torus()
    elif name == "frame":
        v, f = frame()
    else:
        raise ValueError(f"unknown object {name!r} (objects: {', '.join(OBJECTS)})")
    return v, f
