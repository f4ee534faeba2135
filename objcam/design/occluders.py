"""The occluders compared by ``objcam design``, as triangle meshes in world metres over the plane z = 0.

- solid objects (the bundled bunny, a sphere, a user mesh): centred on the z axis, resting on z = 0, scaled so
  the largest side of their bounding box is ``size`` -- comparable size, whatever their proportions;
- the coded-aperture mask: a zero-thickness square of side ``size`` at height ``mask_height``, cut into
  ``mask_cells`` x ``mask_cells`` cells of which a random ``mask_open`` fraction are holes (its stand is left
  out: it would add its own shadows).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from objcam.errors import InputError
from objcam.scene import MeshData


@dataclass
class Occluder:
    """A named occluder mesh. ``kind``: "builtin" or "mesh" (user file, ``source`` its path)."""

    name: str
    mesh: MeshData
    kind: str
    source: str


def normalise(vertices: np.ndarray, size: float) -> np.ndarray:
    """(V, 3) float32: ``vertices`` centred in x, y on the origin (bounding box), lowest point at z = 0 and scaled
    so the largest bounding-box side is ``size`` metres. Raises ValueError for a degenerate (point) mesh."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    extent = float((hi - lo).max())
    if not np.isfinite(extent) or extent <= 0:
        raise ValueError("mesh has no extent")
    v = (v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])) * (size / extent)
    out = v.astype(np.float32)
    out[:, 2] -= out[:, 2].min()  # exactly on the plane after float32 rounding
    return out


def sphere(size: float) -> MeshData:
    """A sphere of diameter ``size`` resting on the plane (icosphere, 5120 faces)."""
    from objcam.synth.assets import icosphere

    v, f = icosphere(4)
    return MeshData(normalise(v, size), np.ascontiguousarray(f, dtype=np.uint32))


def bunny(size: float) -> MeshData:
    """The bundled Stanford bunny (objcam/assets/bunny.ply), largest side ``size``."""
    from objcam.scene import load_mesh
    from objcam.synth.assets import ASSETS

    m = load_mesh(ASSETS / "bunny.ply")
    return MeshData(normalise(m.vertices, size), np.ascontiguousarray(m.faces, dtype=np.uint32))


def user_mesh(path: str | Path, size: float) -> MeshData:
    """A user's mesh file, largest side ``size``; InputError naming the file when it cannot be used."""
    from objcam.scene import load_mesh

    path = Path(path)
    fix = "pass a PLY, OBJ, STL or OFF triangle mesh to --mesh"
    if not path.is_file():
        raise InputError("mesh file not found", path, fix)
    try:
        m = load_mesh(path)
    except InputError as e:  # load_mesh's fix speaks of capture.toml: restate it for --mesh
        raise InputError(str(e).split(" -- ")[0].split(": ", 1)[-1], path, fix) from None
    try:
        v = normalise(m.vertices, size)
    except ValueError:
        raise InputError("mesh is a single point (no extent)", path, fix) from None
    return MeshData(v, np.ascontiguousarray(m.faces, dtype=np.uint32))


def mask_pattern(cells: int, open_fraction: float, seed: int) -> np.ndarray:
    """(cells, cells) bool, True = hole: exactly round(open_fraction * cells^2) holes at random positions."""
    rng = np.random.default_rng([int(seed), 0xC0DE])
    n = cells * cells
    holes = np.zeros(n, bool)
    holes[rng.permutation(n)[: int(round(open_fraction * n))]] = True
    return holes.reshape(cells, cells)


def coded_mask(size: float, height: float, cells: int, open_fraction: float, seed: int) -> MeshData:
    """The coded-aperture mask: a square of side ``size`` at z = ``height``, two triangles per opaque cell
    (cell (i, j) spans x in [-size/2 + j c, -size/2 + (j+1) c], y from +size/2 down by i c, c = size / cells)."""
    holes = mask_pattern(cells, open_fraction, seed)
    c = size / cells
    xs = -size / 2 + c * np.arange(cells + 1)
    ys = size / 2 - c * np.arange(cells + 1)
    gx, gy = np.meshgrid(xs, ys)  # vertex (i, j) at row i (y), column j (x)
    verts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, height)], axis=1).astype(np.float32)
    i, j = np.nonzero(~holes)
    v00 = i * (cells + 1) + j
    v01, v10, v11 = v00 + 1, v00 + cells + 1, v00 + cells + 2
    faces = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)]).astype(np.uint32)
    used = np.unique(faces)  # drop vertices of hole-only corners
    remap = np.full(verts.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return MeshData(verts[used], remap[faces].astype(np.uint32))


def occluders(objects: list[str], meshes: list[Path], size: float, mask_height: float, mask_cells: int,
              mask_open: float, mask_seed: int) -> list[Occluder]:
    """The built-in ``objects`` (bunny, sphere, mask) then every user mesh, with unique names (file stems)."""
    out: list[Occluder] = []
    for name in objects:
        if name == "bunny":
            out.append(Occluder("bunny", bunny(size), "builtin", "objcam/assets/bunny.ply"))
        elif name == "sphere":
            out.append(Occluder("sphere", sphere(size), "builtin", "icosphere"))
        elif name == "mask":
            out.append(Occluder("mask", coded_mask(size, mask_height, mask_cells, mask_open, mask_seed), "builtin",
                                f"{mask_cells}x{mask_cells} cells, {mask_open:g} open, seed {mask_seed}"))
        else:
            raise ValueError(f"unknown occluder {name!r}")
    taken = {o.name for o in out}
    for p in meshes:
        name, k = Path(p).stem or "mesh", 2
        base = name
        while name in taken:
            name, k = f"{base}-{k}", k + 1
        taken.add(name)
        out.append(Occluder(name, user_mesh(p, size), "mesh", str(p)))
    return out
