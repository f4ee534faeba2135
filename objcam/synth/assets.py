"""The ingredients of a synthetic scene: the bundled environment maps and object meshes (objcam/assets), loaded
and scaled, and a binary PLY writer for the meshes a synthetic capture ships.

Shared by every synthetic capture (:mod:`objcam.synth.capture`, :mod:`objcam.synth.full`,
:mod:`objcam.synth.views`, :mod:`objcam.synth.geometry_inputs`, :mod:`objcam.synth.probe`) and by
:mod:`objcam.design.occluders`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from objcam.errors import InputError

ASSETS = Path(__file__).resolve().parent.parent / "assets"


def bundled_envmaps() -> list[str]:
    """Names of the bundled environment maps (objcam/assets/envmaps/*.exr, 128 x 256, standard lat-long files)."""
    return sorted(p.stem for p in (ASSETS / "envmaps").glob("*.exr"))


def load_bundled_envmap(name: str) -> np.ndarray:
    """A bundled environment map (H, 2H, 3) float32 linear radiance on objcam's grid (the file is in the standard
    lat-long convention, objcam.envmap.from_file)."""
    from objcam.envmap import read_latlong

    path = ASSETS / "envmaps" / f"{name}.exr"
    if not path.is_file():
        raise InputError(f"no bundled envmap named {name!r}", None, f"use one of {', '.join(bundled_envmaps())} "
                         "or the path of an EXR in the standard lat-long convention (data_layout.md)")
    return np.ascontiguousarray(read_latlong(path)[..., :3], dtype=np.float32)


# An HDRI's negative texels are compression noise when few and tiny: clamped to 0 with a note. More of them, or
# deeper, is a broken file: refused.
ENV_NEG_FRACTION = 0.01  # of the texels
ENV_NEG_DEPTH = 0.05  # of the map's mean radiance


def clamp_tiny_negatives(env: np.ndarray, path: Path) -> tuple[np.ndarray, str | None]:
    """``env`` with tiny negatives clamped to 0 and a note saying so; InputError for a large negative area."""
    neg = (env < 0).any(axis=2)
    if not neg.any():
        return env, None
    frac, lo = float(neg.mean()), float(env.min())
    mean = float(np.mean(np.maximum(env, 0)))
    if frac > ENV_NEG_FRACTION or -lo > ENV_NEG_DEPTH * max(mean, 1e-30):
        raise InputError(f"envmap has a large negative area ({int(neg.sum()):,} texels, {frac:.2%}, min {lo:.3g}; "
                         f"tolerated: {ENV_NEG_FRACTION:.0%} of texels down to -{ENV_NEG_DEPTH:g} x the mean "
                         f"{mean:.3g})", path, "give a radiance map (values >= 0)")
    note = f"envmap {path.name}: {int(neg.sum()):,} slightly negative texel(s) (min {lo:.3g}) clamped to 0"
    return np.maximum(env, 0.0), note


def load_envmap(spec: str, height: int | None = None, notes: list[str] | None = None) -> np.ndarray:
    """A bundled name or the path of an EXR (H, 2H) in the standard lat-long convention, as objcam's grid, optionally
    resampled to ``height``.
    Tiny negative texels are clamped (``clamp_tiny_negatives``), with a note appended to ``notes``."""
    from objcam.envmap import from_file, resample_to_height
    from objcam.image_io import read_exr

    if spec in bundled_envmaps():
        env = load_bundled_envmap(spec)
    else:
        path = Path(spec)
        if not path.is_file():
            raise InputError("envmap not found", path, f"give a bundled name ({', '.join(bundled_envmaps())}) "
                             "or an EXR in the standard lat-long convention (data_layout.md)")
        env = read_exr(path)  # the standard lat-long convention: from_file below
        if env.shape[2] == 1:
            env = np.repeat(env, 3, axis=2)
        env = env[..., :3]
        if env.shape[1] != 2 * env.shape[0]:
            raise InputError(f"envmap is {env.shape[1]}x{env.shape[0]}, not 2H x H", path,
                             "give an equirectangular map twice as wide as high")
        if not np.all(np.isfinite(env)):
            raise InputError("envmap has NaN or infinite values", path, "re-export it")
        env, note = clamp_tiny_negatives(from_file(env), path)
        if note and notes is not None:
            notes.append(note)
    if height is not None and env.shape[0] != height:
        env = resample_to_height(env.astype(np.float64), height)
    return np.ascontiguousarray(env, dtype=np.float32)


def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh as binary little-endian PLY (float32 x, y, z; int32 vertex_indices), atomically."""
    from objcam.image_io import atomic_write_bytes

    v = np.ascontiguousarray(vertices, dtype="<f4")
    f = np.asarray(faces, dtype=np.int64)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment objcam synth\nelement vertex {len(v)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    rec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"] = 3
    rec["i"] = f
    atomic_write_bytes(path, header + v.tobytes() + rec.tobytes())


def icosphere(subdivisions: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere: vertices (V, 3) float64 and outward-wound faces (F, 3); 20 * 4**subdivisions faces."""
    t = (1.0 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
         (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = np.array(f, dtype=np.int64)
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                p = verts[a] + verts[b]
                verts.append(p / np.linalg.norm(p))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = np.array(new, dtype=np.int64)
    return np.array(verts), faces.astype(np.uint32)


def object_mesh(spec: str, height: float) -> tuple[np.ndarray, np.ndarray]:
    """The object as (vertices (V, 3) float32 metres, faces (F, 3) uint32): ``spec`` "bunny", "sphere" or a mesh
    path; scaled to ``height`` metres, centred on the origin in x and y (bounding box), lowest vertex at z = 0."""
    from objcam.scene import load_mesh

    if spec == "sphere":
        v, f = icosphere(4)
    elif spec == "bunny":
        m = load_mesh(ASSETS / "bunny.ply")
        v, f = m.vertices.astype(np.float64), m.faces
    else:
        m = load_mesh(spec)
        v, f = m.vertices.astype(np.float64), m.faces
    lo, hi = v.min(axis=0), v.max(axis=0)
    if hi[2] - lo[2] <= 0:
        raise InputError("mesh is flat in z; cannot scale it to a height", spec)
    v = (v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])) * (height / (hi[2] - lo[2]))
    v = v.astype(np.float32)
    v[:, 2] -= v[:, 2].min()  # exactly 0 after the float32 rounding
    return v, np.ascontiguousarray(f, dtype=np.uint32)
