"""Bake the joint solve's per-pixel albedo into a UV texture of each surface whose albedo was unknown, so that the
exported scene renders the solve's prediction ``rho_p (A'_p x)`` and not a placeholder's.

The solve estimates the albedo per pooled pixel (``solve/<target>/albedo.exr``, (H', W', 3), valid where
``albedo_mask.png`` is 255). Here every texel centre of the surface is projected into each camera at the pooled
size; it takes the albedo of the pooled pixel it falls in when that pixel's albedo was estimated, the texel faces
the camera and nothing occludes it (a Mitsuba ray test towards the camera centre). Seen by several cameras, a
texel takes the camera that sees it finest (the smallest pooled-pixel area on the surface); texels no camera saw
(outside every frame, hidden, in silhouette pixels the solve left out, uncovered atlas gutter) hold their nearest
seen texel's value (objcam.geometry.uv.fill_gutter).

Resolution rule: a pooled pixel's render is the mean of the texture over its footprint, so a texel straddling two
pixels' footprints gives part of one pixel the other's albedo. That error falls as 1 / (texels per pixel): the
texel side is the smallest pooled-pixel footprint (depth / fx' at the nearest seen point of the surface) over
``TEXELS_PER_PIXEL``, the texture side capped at ``MAX_SIDE`` (the achieved ratio is recorded).

UVs: a flat axis-aligned rectangle (the support plane) gets a 3 x 3 grid of quads whose centre quad is the
rectangle the cameras saw, with planar UVs over it; the outer quads clamp to its border texels (what Mitsuba's
clamp lookup would do, written into the mesh so that viewers, which repeat, show the same). Any other surface
gets an xatlas atlas at the rule's texel density (vertices split along seams; faces kept in order).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.scene import MeshData

TEXELS_PER_PIXEL = 16  # texel side = smallest pooled-pixel footprint / this (module docstring)
MAX_SIDE = 4096  # texture side cap, texels


@dataclass
class AlbedoView:
    """One camera's estimated albedo: ``camera`` at the pooled image size, ``albedo`` (H', W', 3) linear,
    ``estimated`` (H', W') bool: the pixels whose albedo the solve estimated."""

    camera: Camera
    albedo: np.ndarray
    estimated: np.ndarray


@dataclass
class BakedAlbedo:
    """A surface with UVs and its baked texture (R, C, 3) linear in [0, 1] over them."""

    mesh: MeshData
    texture: np.ndarray
    record: dict = field(default_factory=dict)  # for export.json: uv, size, texel_m, texels_per_pixel, seen


def pooled_camera(cam: Camera, f: int) -> Camera:
    """``cam`` at the f x f pooled image size: pooled pixel j covers full pixels j f .. j f + f - 1, centred at
    j f + (f - 1) / 2 (pixel centres at integer coordinates, as Camera.project)."""
    f = int(f)
    h = (f - 1) / 2.0
    return Camera(width=cam.width // f, height=cam.height // f, fx=cam.fx / f, fy=cam.fy / f, cx=(cam.cx - h) / f,
                  cy=(cam.cy - h) / f, world_from_camera=cam.world_from_camera)


def albedo_views(solve_dir: Path, targets: list, downsample: dict[str, int],
                 scales: dict[str, float] | None = None) -> list[AlbedoView]:
    """An AlbedoView per target of ``targets`` (scene targets) with an ``albedo.exr`` in ``solve_dir/<name>``, its
    albedo times ``scales[name]`` (objcam.export.scale; 1 when absent)."""
    from PIL import Image

    from objcam.image_io import read_exr

    out = []
    for t in targets:
        d = Path(solve_dir) / t.name
        if not (d / "albedo.exr").is_file() or not (d / "albedo_mask.png").is_file():
            continue
        alb = np.clip(read_exr(d / "albedo.exr")[..., :3].astype(np.float64), 0.0, None)
        alb = alb * (scales or {}).get(t.name, 1.0)
        mask = np.asarray(Image.open(d / "albedo_mask.png"))
        mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
        cam = pooled_camera(t.camera, downsample[t.name])
        if alb.shape[:2] != (cam.height, cam.width) or mask.shape != alb.shape[:2]:
            continue  # not this transport's pooled size: nothing to project
        out.append(AlbedoView(cam, alb, mask))
    return out


def _is_rectangle(mesh: MeshData) -> bool:
    """Flat (z constant), facing +z, and exactly covering its xy bounding box."""
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    size = float(np.max(hi[:2] - lo[:2]))
    if size <= 0 or hi[2] - lo[2] > 1e-6 * size:
        return False
    tri = v[np.asarray(mesh.faces, np.int64)]
    cz = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2] / 2.0
    return bool(np.all(cz >= 0) and abs(cz.sum() - np.prod(hi[:2] - lo[:2])) <= 1e-6 * size * size)


def _seen(mesh: MeshData, views: list[AlbedoView], rays_all, rays_mesh) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) where estimated pixel centres' rays first hit ``mesh``, and each one's pooled-pixel
    footprint (N,) in metres (depth / fx')."""
    pts, foot = [], []
    for v in views:
        rows, cols = np.nonzero(v.estimated)
        if len(rows) == 0:
            continue
        o, d = v.camera.rays(cols.astype(np.float64), rows.astype(np.float64))
        t_all, t_m = rays_all.hit_distance(o, d), rays_mesh.hit_distance(o, d)
        on = np.isfinite(t_m) & (np.abs(t_m - t_all) <= 1e-5 * np.maximum(t_m, 1e-3))
        p = o[on] + d[on] * t_m[on, None]
        depth = (p - v.camera.centre) @ v.camera.matrix[:3, 2]
        pts.append(p)
        foot.append(depth / v.camera.fx)
    if not pts:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(pts), np.concatenate(foot)


def _rectangle_uv(mesh: MeshData, seen: np.ndarray,
                  texel: float) -> tuple[MeshData, np.ndarray, tuple[int, int], float]:
    """The 3 x 3 quad grid (module docstring) over ``mesh``'s rectangle, the seen rectangle (``seen`` points
    (N, 3) and a texel's margin) in its centre; its texel centre points (R*C, 3) row-major, (R, C), and the larger
    texel side achieved (metres)."""
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi, z = v.min(axis=0)[:2], v.max(axis=0)[:2], float(v[0, 2])
    s_lo = np.clip(seen.min(axis=0)[:2] - texel, lo, hi)
    s_hi = np.clip(seen.max(axis=0)[:2] + texel, lo, hi)
    span = np.maximum(s_hi - s_lo, texel)
    cols, rows = (int(min(MAX_SIDE, max(1, np.ceil(s / texel)))) for s in span)
    xs, ys = np.array([lo[0], s_lo[0], s_lo[0] + span[0], hi[0]]), np.array([lo[1], s_lo[1], s_lo[1] + span[1], hi[1]])
    gx, gy = np.meshgrid(xs, ys, indexing="xy")  # (4, 4): row j = ys[j], column i = xs[i]
    verts = np.stack([gx.ravel(), gy.ravel(), np.full(16, z)], 1)
    uv = np.stack([np.clip((verts[:, 0] - s_lo[0]) / span[0], 0, 1),
                   np.clip((s_lo[1] + span[1] - verts[:, 1]) / span[1], 0, 1)], 1)  # row 0 towards +y
    faces = []
    for j in range(3):
        for i in range(3):
            a, b, c, d = 4 * j + i, 4 * j + i + 1, 4 * (j + 1) + i + 1, 4 * (j + 1) + i
            faces += [[a, b, c], [a, c, d]]  # counter-clockwise seen from +z
    cx = s_lo[0] + (np.arange(cols) + 0.5) / cols * span[0]
    cy = s_lo[1] + span[1] - (np.arange(rows) + 0.5) / rows * span[1]
    yy, xx = np.meshgrid(cy, cx, indexing="ij")
    centres = np.stack([xx.ravel(), yy.ravel(), np.full(rows * cols, z)], 1)
    out = MeshData(verts.astype(np.float32), np.asarray(faces, np.uint32), uv.astype(np.float32))
    return out, centres, (rows, cols), float(max(span[0] / cols, span[1] / rows))


def _atlas_uv(mesh: MeshData, texel: float) -> tuple[MeshData, np.ndarray, np.ndarray, np.ndarray, float]:
    """xatlas at 1 / ``texel`` texels per metre (coarser when the atlas would pass MAX_SIDE): the UV mesh, the
    covered texels' centre points (N, 3) and face normals (N, 3), the covered mask (R, C), the texel side achieved."""
    from objcam.geometry.uv import atlas_sized, rasterize, surface_points

    density = 1.0 / texel
    uvm, size, density = atlas_sized(mesh, texels_per_unit=density)
    while max(size) > MAX_SIDE:  # xatlas sizes the atlas from the density: lower it until the atlas fits
        uvm, size, density = atlas_sized(mesh, texels_per_unit=density * 0.95 * MAX_SIDE / max(size))
    face, bary = rasterize(uvm, size)
    pts, nrm = surface_points(uvm, face, bary)
    return uvm, pts, nrm, face >= 0, 1.0 / density


def _sample(points: np.ndarray, normals: np.ndarray, views: list[AlbedoView], rays_all, offset: float,
            chunk: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) albedo and (N,) seen of surface ``points`` with unit ``normals`` (either side): from the camera that
    sees each finest (module docstring). In chunks of ``chunk`` points (a 4096^2 texture's temporaries)."""
    if len(points) > chunk:
        parts = [_sample(points[s:s + chunk], normals[s:s + chunk], views, rays_all, offset, chunk)
                 for s in range(0, len(points), chunk)]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    n = len(points)
    best = np.full(n, np.inf)
    out = np.zeros((n, 3), np.float32)
    for v in views:
        cam = v.camera
        to_c = cam.centre - points
        dist = np.linalg.norm(to_c, axis=1)
        d = to_c / np.maximum(dist[:, None], 1e-12)
        cos = np.einsum("ij,ij->i", normals, d)
        depth = -(to_c @ cam.matrix[:3, 2])
        uv = cam.project(points)
        col, row = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        cand = (depth > 0) & (np.abs(cos) > 1e-3) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        idx = np.nonzero(cand)[0]
        idx = idx[v.estimated[row[idx], col[idx]]]
        score = (depth[idx] / cam.fx) ** 2 / np.abs(cos[idx])  # the pooled pixel's area on the surface
        idx, score = idx[score < best[idx]], score[score < best[idx]]
        if len(idx) == 0:
            continue
        side = np.sign(cos[idx])[:, None] * normals[idx]  # the camera's side of the surface
        occ = rays_all.occluded(points[idx] + offset * side, d[idx], dist[idx] - 2 * offset)
        idx, score = idx[~occ], score[~occ]
        best[idx] = score
        out[idx] = v.albedo[row[idx], col[idx]]
    return out, np.isfinite(best)


def bake_albedo(mesh: MeshData, others: list[MeshData], views: list[AlbedoView]) -> BakedAlbedo | None:
    """``mesh``'s albedo baked from ``views`` (module docstring), ``others`` the scene's other meshes (occluders);
    None when no estimated pixel sees the mesh."""
    from objcam.geometry.raycast import RayScene
    from objcam.geometry.uv import fill_gutter

    rays_all, rays_mesh = RayScene([mesh, *others]), RayScene([mesh])
    seen_pts, foot = _seen(mesh, views, rays_all, rays_mesh)
    if len(seen_pts) == 0:
        return None
    texel = float(foot.min()) / TEXELS_PER_PIXEL
    allv = np.concatenate([np.asarray(m.vertices, np.float64) for m in (mesh, *others)])
    offset = 1e-5 * float(np.linalg.norm(allv.max(axis=0) - allv.min(axis=0)))  # self-hits: scene size relative
    if _is_rectangle(mesh):
        uvm, pts, size, achieved = _rectangle_uv(mesh, seen_pts, texel)
        nrm = np.broadcast_to(np.array([0.0, 0.0, 1.0]), pts.shape)  # a view: no (R*C, 3) copy
        covered = np.ones(size, bool)
        uv_kind = "planar over the seen rectangle (3 x 3 quads, the outer ones clamped to its border)"
    else:
        uvm, pts, nrm, covered, achieved = _atlas_uv(mesh, texel)
        size = covered.shape
        uv_kind = "xatlas (vertices split along seams, faces in objcam's order)"
    alb, seen = _sample(pts, nrm, views, rays_all, offset)
    img = np.zeros((*size, 3), np.float32)
    ok = np.zeros(size, bool)
    img[covered], ok[covered] = alb, seen
    img = fill_gutter(img, ok)
    rec = {"uv": uv_kind, "texture_size": [int(size[0]), int(size[1])], "texel_m_rule": texel,
           "texels_per_pixel_rule": TEXELS_PER_PIXEL, "texel_m": achieved,
           "texels_per_pixel": float(foot.min()) / achieved,
           "texels_seen": int(ok.sum()), "texels_covered": int(covered.sum()),
           "fill": "texels no camera saw hold their nearest seen texel's value"}
    return BakedAlbedo(uvm, np.clip(img, 0.0, 1.0).astype(np.float32), rec)
