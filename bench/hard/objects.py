"""The suite's three objects, in world metres resting on z = 0, centred on the z axis: the bundled bunny, a torus
lying flat (a hole through which the sky is seen) and a chair-like frame (thin legs and rails, a slab seat); and
the held-out design's three (bench/hard/design.py, ``HELD_OUT``), never used to choose a parameter: a trefoil knot
(a thin tube that crosses itself), a mug (a concave cup with a handle) and a sphere (the method's smooth occluder).

All but the bunny are generated here (no licence needed); the bunny is objcam/assets/bunny.ply (Stanford
Bunny, credit the Stanford Computer Graphics Laboratory; see objcam/assets/LICENSES.md), read with a small PLY
reader of its own so that nothing of objcam's scene code is involved.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

OBJECTS = ("bunny", "torus", "frame")
HELD_OUT_OBJECTS = ("knot", "mug", "sphere")
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


def _oriented(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v, f) with the faces wound so that a closed mesh's signed volume is positive (normals outward)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
    return v, (f if vol > 0 else f[:, ::-1].copy())


def revolve(profile: np.ndarray, n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The surface swept by the (r, z) polyline ``profile`` (P, 2) about the z axis in ``n`` steps; its first and
    last points on the axis (r = 0), so the surface is closed; normals outward."""
    profile = np.asarray(profile, np.float64)
    if profile[0, 0] != 0 or profile[-1, 0] != 0:
        raise ValueError("revolve: the profile must start and end on the axis")
    u = 2 * np.pi * np.arange(n) / n
    ring = profile[1:-1]  # (P - 2, 2): one ring of n vertices each
    v = np.concatenate([[[0, 0, profile[0, 1]]],
                        np.stack([ring[:, :1] * np.cos(u), ring[:, :1] * np.sin(u),
                                  np.repeat(ring[:, 1:], n, axis=1)], -1).reshape(-1, 3),
                        [[0, 0, profile[-1, 1]]]])
    last = len(v) - 1
    j = np.arange(n)
    faces = [np.stack([np.zeros(n, int), 1 + (j + 1) % n, 1 + j], -1)]
    for k in range(len(ring) - 1):
        a, b = 1 + k * n + j, 1 + k * n + (j + 1) % n
        faces += [np.stack([a, b, b + n], -1), np.stack([a, b + n, a + n], -1)]
    k = len(ring) - 1
    faces.append(np.stack([1 + k * n + j, 1 + k * n + (j + 1) % n, np.full(n, last)], -1))
    return _oriented(v, np.concatenate(faces))


def tube(curve: np.ndarray, radius: float, closed: bool, up=(0.0, 0.0, 1.0), m: int = 16
         ) -> tuple[np.ndarray, np.ndarray]:
    """A tube of ``radius`` along the polyline ``curve`` (P, 3), a loop when ``closed`` (else open-ended); each
    cross-section in the plane normal to the curve, framed by the curve's tangent and the direction ``up`` (the
    curve must never run along it)."""
    curve = np.asarray(curve, np.float64)
    t = (np.roll(curve, -1, 0) - np.roll(curve, 1, 0)) if closed else np.gradient(curve, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    nrm = np.cross(t, np.asarray(up, np.float64))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    bin_ = np.cross(t, nrm)
    w = 2 * np.pi * np.arange(m) / m
    v = (curve[:, None] + radius * (np.cos(w)[None, :, None] * nrm[:, None] + np.sin(w)[None, :, None]
                                    * bin_[:, None])).reshape(-1, 3)
    p = len(curve)
    i, j = np.meshgrid(np.arange(p if closed else p - 1), np.arange(m), indexing="ij")
    a, b = i * m + j, ((i + 1) % p) * m + j
    c, d = ((i + 1) % p) * m + (j + 1) % m, i * m + (j + 1) % m
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f[:, ::-1].copy()  # (i, j) -> (i + 1, j) -> (i + 1, j + 1) turns about -t x (the ring's way): inward


def knot(size: float = SIZE, radius: float = 0.004, n: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """A trefoil knot lying on z = 0: a tube of ``radius`` along (sin t + 2 sin 2t, cos t - 2 cos 2t, -sin 3t),
    ``size`` across (about a third as tall)."""
    t = 2 * np.pi * np.arange(n) / n
    c = np.stack([np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)], -1)
    c *= (size - 2 * radius) / np.ptp(c[:, :2], axis=0).max()
    c[:, 2] -= c[:, 2].min() - radius
    return tube(c, radius, closed=True)


def mug(size: float = SIZE) -> tuple[np.ndarray, np.ndarray]:
    """A mug ``size`` tall: a cup 0.6 size across with 4-mm walls and a 6-mm floor, open at the top, and a
    handle (a 3-mm tube on a half ring) on its +x side."""
    r_out, wall, floor = 0.3 * size, 0.004, 0.006
    v, f = revolve([(0, 0), (r_out, 0), (r_out, size), (r_out - wall, size), (r_out - wall, floor), (0, floor)])
    a = 0.3 * size  # the handle's ring radius about its centre on the outer wall, halfway up
    u = np.radians(np.linspace(-95, 95, 48))
    # the ends reach 1 mm into the 4-mm wall, so the open tube's rims are hidden inside it
    hv, hf = tube(np.stack([r_out + a * np.cos(u), np.zeros_like(u), 0.5 * size + a * np.sin(u)], -1), 0.003,
                  closed=False, up=(0.0, 1.0, 0.0))
    return np.concatenate([v, hv]), np.concatenate([f, hf + len(v)])


def sphere(size: float = SIZE, n: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A sphere ``size`` across, resting on z = 0 at one point."""
    a = np.linspace(-np.pi / 2, np.pi / 2, n + 1)
    r = 0.5 * size * np.cos(a)
    r[[0, -1]] = 0.0  # on the axis exactly
    return revolve(np.stack([r, 0.5 * size * (1 + np.sin(a))], -1), 2 * n)


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
    elif name in HELD_OUT_OBJECTS:
        v, f = {"knot": knot, "mug": mug, "sphere": sphere}[name]()
    else:
        raise ValueError(f"unknown object {name!r} (objects: {', '.join(OBJECTS + HELD_OUT_OBJECTS)})")
    return v, f
