"""Target photos taken from one tripod position get one camera.

SfM poses every photo on its own, so two targets shot from one tripod (the same framing under another light) come
out a fraction of a pixel apart: on tests/test_full_run_two.py's capture 0.36 mm and 0.06 deg, about 0.3 px. The
transport builds one A per distinct camera and the solve fits together only the targets of one camera, so each
illumination became a problem of its own, and with an unknown albedo one photo cannot separate albedo from light.

Rule: targets whose cameras have the same intrinsics and whose poses move the image of the support plane (z = 0,
where the shadows are) by at most ``max_px`` pixels are one position; each of them gets the group's mean pose.
SfM's own pose noise put two shots from one tripod 0.2-0.5 px apart with the camera 40 deg up and 1.6 px apart
(1.5 mm, 0.23 deg; each 2 mm from the truth) 25 deg up, on 320 px wide images; the stage's default, 5 px, is three
times that, and the mean pose of the group is nearer the truth than either. A tripod moved to another position
(centimetres) shifts the plane by tens to hundreds of pixels, and a pixel of SfM's copies (at most 1,600 px wide)
is a fifth of a pixel or less of the image the transport models by default on a DSLR photo.
"""

from __future__ import annotations

import numpy as np

from objcam.camera import Camera

#: Pixels along each side of the image at which the plane's displacement is measured.
GRID = 9


def _plane_points(cam: Camera, grid: int = GRID) -> tuple[np.ndarray, np.ndarray]:
    """Points of the plane z = 0 seen by ``cam`` at a grid x grid lattice of its pixels: (P, 3) world metres and
    their (P, 2) pixel coordinates; pixels whose ray misses the plane (at or above the horizon) are left out."""
    u = np.linspace(0.0, cam.width - 1.0, grid)
    v = np.linspace(0.0, cam.height - 1.0, grid)
    uu, vv = np.meshgrid(u, v)
    o, d = cam.rays(uu.ravel(), vv.ravel())
    down = d[:, 2] < -1e-9
    t = np.where(down, -o[:, 2] / np.where(down, d[:, 2], -1.0), -1.0)
    hit = t > 0
    return o[hit] + t[hit, None] * d[hit], np.stack([uu.ravel(), vv.ravel()], axis=1)[hit]


def plane_displacement_px(a: Camera, b: Camera, grid: int = GRID) -> float:
    """Largest image displacement, in pixels, of the support plane (z = 0) between cameras ``a`` and ``b``: the
    plane points each camera sees at a grid x grid lattice of its pixels, projected by the other camera (both
    ways). inf when either camera sees fewer than 4 of those points in front of the other."""
    worst = 0.0
    for c1, c2 in ((a, b), (b, a)):
        pts, pix = _plane_points(c1, grid)
        depth = (pts - c2.centre) @ c2.matrix[:3, 2]
        front = depth > 0
        if front.sum() < 4:
            return float("inf")
        moved = c2.project(pts[front]) - pix[front]
        worst = max(worst, float(np.sqrt((moved ** 2).sum(axis=1)).max()))
    return worst


def _same_intrinsics(a: Camera, b: Camera) -> bool:
    if (a.width, a.height) != (b.width, b.height):
        return False
    ka, kb = np.array([a.fx, a.fy, a.cx, a.cy]), np.array([b.fx, b.fy, b.cx, b.cy])
    return bool(np.allclose(ka, kb, rtol=1e-9, atol=1e-9 * max(a.width, a.height)))


def mean_camera(cams: list[Camera]) -> Camera:
    """One camera for poses of one position: the first camera's intrinsics, the mean centre and the rotation
    nearest (Frobenius) to the mean rotation matrix (the chordal L2 mean)."""
    mats = np.stack([c.matrix for c in cams])
    u, _, vt = np.linalg.svd(mats[:, :3, :3].mean(axis=0))
    r = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = mats[:, :3, 3].mean(axis=0)
    return cams[0].model_copy(update={"world_from_camera": m.tolist()})


def same_position_groups(cams: dict[str, Camera], max_px: float) -> list[list[str]]:
    """Names of ``cams`` grouped by position, in name order: a camera joins the first group all of whose members
    share its intrinsics and lie within ``max_px`` (:func:`plane_displacement_px`, pixels of those cameras), else
    starts a group. max_px = 0: every camera alone."""
    groups: list[list[str]] = []
    for name in sorted(cams):
        c = cams[name]
        for g in groups:
            if max_px > 0 and all(_same_intrinsics(c, cams[o]) and plane_displacement_px(c, cams[o]) <= max_px
                                  for o in g):
                g.append(name)
                break
        else:
            groups.append([name])
    return groups


def merge_same_position(cams: dict[str, Camera], max_px: float) -> tuple[dict[str, Camera], list[dict]]:
    """``cams`` with the cameras of each position (:func:`same_position_groups`) replaced by their
    :func:`mean_camera`, and a record per position of two or more targets: {"targets": names, "displacement_px":
    the largest displacement between two of them before the merge}."""
    out = dict(cams)
    records = []
    for g in same_position_groups(cams, max_px):
        if len(g) < 2:
            continue
        shared = mean_camera([cams[n] for n in g])
        worst = max(plane_displacement_px(cams[a], cams[b]) for i, a in enumerate(g) for b in g[i + 1:])
        for n in g:
            out[n] = shared
        records.append({"targets": g, "displacement_px": round(worst, 4)})
    return out, records


def nearest_separate(cams: dict[str, Camera], merged: dict[str, Camera]) -> dict | None:
    """The two targets of different cameras after the merge (``merged``) that SfM posed nearest to each other
    (same intrinsics; :func:`plane_displacement_px` of their ``cams``): {"targets": [a, b], "displacement_px"};
    None when there is no such pair. What to look at when illuminations meant to share a tripod were not merged."""
    best = None
    names = sorted(cams)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if merged[a] == merged[b] or not _same_intrinsics(cams[a], cams[b]):
                continue
            d = plane_displacement_px(cams[a], cams[b])
            if np.isfinite(d) and (best is None or d < best["displacement_px"]):
                best = {"targets": [a, b], "displacement_px": round(d, 4)}
    return best
