"""Known-shape pose refined against the views' silhouettes: the model's outline in every view should run along the
photographed object's outline.

Why: the carved hull, which the first registration aligns to (objcam.geometry.register), is biased outward
wherever the object is concave and wherever a view's mask was generous, so ICP to it leaves ~1-2 degrees of tilt
and yaw (measured 2 degrees, 1 mm mean vertex error on the bench). The silhouettes themselves are unbiased
(measured from every side), so the pose that best puts the model's outline on them is (0.2 mm on the bench).

Method (Gauss-Newton on the rigid pose, 5-10 iterations):
1. Rim points, per view: midpoints of the model's contour edges (one adjacent face towards the camera, one away)
   that lie on its *outer* outline: nothing of the model in front of them or behind them along the ray, just
   outside the surface (two Mitsuba ray tests). Points below ``min_height`` are left out: there the masks cannot
   separate the object from the plane (objcam.geometry.silhouette). So are the rims of holes in the model's
   projected silhouette (a ring's, a mug handle's): the masks fill every enclosed region by design (patches of
   the object that match the plane by chance), and the paper seen through a hole is hidden from most views
   anyway (a dark torus: 53% of its rim points on the masks' outlines, refused; 96% on its outer outline).
2. Residual of a rim point: the observed mask's signed distance (pixels, objcam.geometry.maskfield) at its
   projection, minus one global offset ``b`` (a mask that is uniformly a fraction of a pixel too generous or too
   tight is not a pose error), in metres at the point's depth. Zero when the outlines agree.
3. Jacobian from the distance image's gradient through the projection; outliers (beyond ``inlier_px`` or three
   robust sigmas: mask errors, the band near the plane) are left out of each step; damped normal equations. With
   the views' images, each rim point is weighted by the image's contrast across the outline: where the object
   looks like what is behind it the mask's outline is unreliable (measured 0.34 -> 0.30 mm with earlier masks).
4. After each step the model is lowered or raised to rest on z = 0 (the world frame's support).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.scene import MeshData


class SilhouetteFitParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(True, description="refine the hull registration against the views' silhouettes")
    # the contour set changes from step to step, so steps level off at ~1e-4 rad after 5-10 iterations
    iterations: int = Field(20, ge=1, description="Gauss-Newton iterations at most")
    max_faces: int = Field(30000, ge=500, description="the model is decimated to this many faces for the fit")
    min_height: float = Field(4e-3, ge=0, description="rim points below this height (metres) are left out")
    inlier_px: float = Field(2.0, gt=0, description="residuals within this many pixels are always inliers")
    smooth_px: float = Field(0.7, ge=0, description="Gaussian blur of the distance images (pixel quantisation)")
    damping: float = Field(1e-3, ge=0, description="Levenberg damping, relative to the normal matrix's diagonal")
    tol_rad: float = Field(1.5e-4, gt=0, description="converged when a step rotates less than this (radians) ...")
    tol_m: float = Field(5e-6, gt=0, description="... and moves less than this across (metres)")
    contrast_px: float = Field(2.0, gt=0, description="the image is compared this many pixels either side of the "
                               "outline")
    contrast_ref: float = Field(0.15, gt=0, description="relative contrast across the outline at which a rim "
                                "point gets half weight (a mask's outline is only as sure as that contrast)")
    skip_hole_rims: bool = Field(True, description="leave out the rims of holes in the model's projected "
                                 "silhouette (a ring's, a handle's): the masks fill the paper seen through them")


class SilhouetteFit(BaseModel):
    """The correction found: ``world_from_world`` (4x4 rigid) maps the model's initial world pose to the refined
    one. Residuals of the last step's inliers: ``rms_px`` in pixels, ``rms_mm`` at the rim points' depth."""

    model_config = ConfigDict(frozen=True)
    world_from_world: list[list[float]]
    rotation_deg: float  # size of the correction's rotation
    translation_mm: float  # movement of the model's centroid
    rms_px: float
    rms_mm: float
    offset_px: float  # fitted mask offset (positive: masks larger than the model's outline)
    points: int  # rim points over all views in the last step
    inlier_fraction: float  # rim points used by the last step (within inlier_px or three robust sigmas)
    agree_fraction: float  # rim points within inlier_px of the silhouette's outline (contrast-weighted)
    iterations: int


class _ViewData:
    """One view's signed distance image (pixels), its gradient, where it carries evidence, and its camera."""

    def __init__(self, mask: np.ndarray, known: np.ndarray | None, cam, smooth_px: float,
                 image: np.ndarray | None = None):
        import cv2

        from objcam.geometry.maskfield import signed_distance

        sd = signed_distance(mask)
        if smooth_px > 0:
            sd = cv2.GaussianBlur(sd, (0, 0), smooth_px)
        self.sd = sd
        gv, gu = np.gradient(sd)
        self.grad = np.stack([gu, gv], axis=2).astype(np.float32)
        self.known = known
        self.cam = cam
        cw = np.linalg.inv(cam.matrix)
        self.r, self.t = cw[:3, :3], cw[:3, 3]
        self.centre = cam.centre
        self.grey = None
        if image is not None:  # for the contrast across the outline: grey, lightly blurred (noise)
            self.grey = cv2.GaussianBlur(np.asarray(image, np.float32)[..., :3].mean(axis=2), (0, 0), 1.0)
            self.floor = 0.05 * float(np.median(self.grey))


def _manifold_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges shared by exactly two faces: (E, 2) vertex indices and (E, 2) the two faces."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(len(f)), 3)
    e.sort(axis=1)
    key = e[:, 0] * (int(f.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    key, e, owner = key[order], e[order], owner[order]
    _, start, count = np.unique(key, return_index=True, return_counts=True)
    s = start[count == 2]
    return e[s], np.stack([owner[s], owner[s + 1]], axis=1)


def _contours(v: np.ndarray, faces: np.ndarray, fn: np.ndarray, edges, view: _ViewData, min_height: float):
    """The contour edges of the model seen from ``view`` above ``min_height``: their indices into ``edges`` (K,),
    midpoints (K, 3) and a test point half a pixel's footprint outside the surface, across the ray (K, 3).

    v: (V, 3) vertices and fn: (F, 3) unit face normals at the current pose; faces (F, 3); edges:
    :func:`_manifold_edges`."""
    ev, ef = edges
    facing = np.einsum("ij,ij->i", fn, v[faces[:, 0]] - view.centre) < 0
    cont = np.nonzero(facing[ef[:, 0]] != facing[ef[:, 1]])[0]
    p = 0.5 * (v[ev[cont, 0]] + v[ev[cont, 1]])
    keep = p[:, 2] >= min_height
    cont, p = cont[keep], p[keep]
    d = p - view.centre
    dist = np.linalg.norm(d, axis=1)
    d /= np.maximum(dist, 1e-12)[:, None]
    m = fn[ef[cont, 0]] + fn[ef[cont, 1]]
    m -= np.einsum("ij,ij->i", m, d)[:, None] * d
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    return cont, p, p + (0.5 * dist / view.cam.fx)[:, None] * m


def silhouette_holes(v: np.ndarray, faces: np.ndarray, cam, margin_px: int = 3) -> np.ndarray:
    """(H, W) bool: the pixels of camera ``cam`` enclosed by the projected silhouette of the mesh (v (V, 3) world
    metres, faces (F, 3)) but not covered by it -- its holes -- grown by ``margin_px`` (the pose moves a little
    during the fit). Holes of a pixel or so (rasterisation cracks) are closed first. All False when a vertex is
    behind the camera."""
    import cv2

    from objcam.geometry.silhouette import fill_holes

    h, w = int(cam.height), int(cam.width)
    if np.any((v - cam.centre) @ np.asarray(cam.matrix)[:3, 2] <= 0):  # depth along the optical axis
        return np.zeros((h, w), bool)
    uv = cam.project(v)
    # fixed point with 4 fractional bits, pixel centres at integers (cv2's convention)
    tri = np.rint(np.clip(uv, -4 * w, 5 * w)[faces] * 16).astype(np.int32)
    sil = np.zeros((h, w), np.uint8)
    for t in tri:  # union of the triangles (cv2.fillPoly's even-odd rule would cut their overlaps)
        cv2.fillConvexPoly(sil, t, 1, lineType=cv2.LINE_8, shift=4)
    sil = cv2.morphologyEx(sil, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    holes = (fill_holes(sil) & ~sil).astype(np.uint8)  # as the masks fill them
    if margin_px > 0 and holes.any():
        holes = cv2.dilate(holes, np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8))
    return holes.astype(bool)


def _outer(rays, centres: np.ndarray, q: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(K,) bool: whether the ray from each camera centre (K, 3) through the test point q (K, 3) (current pose) meets
    nothing of the model, before q or after it: q's contour edge is on the model's outer outline. ``rays`` holds
    the model at its initial pose, which the current pose maps by x -> r x + t (one batch: Mitsuba's launch
    overhead dominates small calls)."""
    c0 = (centres - t) @ r  # x0 = r^T (x - t)
    q0 = (q - t) @ r
    seg = q0 - c0
    length = np.linalg.norm(seg, axis=1)
    hit = rays.occluded(np.concatenate([c0, q0]), np.concatenate([seg, seg]),
                        np.concatenate([length * (1 - 1e-4), np.full(len(q0), np.inf)]))
    return ~hit[:len(q0)] & ~hit[len(q0):]


def _contrast(view: _ViewData, u: np.ndarray, w: np.ndarray, du: np.ndarray, dw: np.ndarray, s: float) -> np.ndarray:
    """Relative contrast (N,) of the view's image across the outline at (u, w) (N,) pixels, outward direction
    (du, dw) (N,) unit: |outside - inside| / (mean + floor), ``s`` pixels either side."""
    from objcam.geometry.maskfield import bilinear

    g_out = bilinear(view.grey, u + s * du, w + s * dw)
    g_in = bilinear(view.grey, u - s * du, w - s * dw)
    return np.abs(g_out - g_in) / (0.5 * (g_out + g_in) + view.floor)


def fit(model: MeshData, masks: list, cams: list, params: SilhouetteFitParams | None = None,
        images: list | None = None) -> SilhouetteFit:
    """Refine the pose of ``model`` (world metres, already near its place: the hull registration) so that its
    outline agrees with the silhouettes. masks: per view (mask, known) (H, W) bool pairs or a mask alone; cams:
    the views' cameras (objcam Camera); images: the views' linear images (H, W, 3), optional: where given, each
    rim point is weighted by the image's contrast across the outline there (where the object looks like what is
    behind it, the masks' outline is unreliable: the object's flanks against their own shadow, its lit top
    against the paper)."""
    from objcam.threads import single_blas_thread

    with single_blas_thread():  # small solves: BLAS threads only contend (objcam.threads)
        return _fit(model, masks, cams, params, images)


def _fit(model: MeshData, masks: list, cams: list, params: SilhouetteFitParams | None,
         images: list | None) -> SilhouetteFit:
    from scipy.spatial.transform import Rotation

    from objcam.geometry.maskfield import bilinear
    from objcam.geometry.raycast import RayScene
    from objcam.geometry.surface import decimate

    params = params or SilhouetteFitParams()
    m = decimate(MeshData(np.asarray(model.vertices, np.float32), np.asarray(model.faces, np.uint32)),
                 params.max_faces)
    v0 = m.vertices.astype(np.float64)
    faces = np.asarray(m.faces, np.int64)
    edges = _manifold_edges(faces)
    rays = RayScene([m])
    images = images if images is not None else [None] * len(cams)
    views = [_ViewData(*(mk if isinstance(mk, tuple) else (mk, None)), c, params.smooth_px, im)
             for mk, c, im in zip(masks, cams, images)]
    n0 = np.cross(v0[faces[:, 1]] - v0[faces[:, 0]], v0[faces[:, 2]] - v0[faces[:, 0]])
    n0 /= np.maximum(np.linalg.norm(n0, axis=1, keepdims=True), 1e-30)
    # at the initial pose (the fit moves it ~1-2 degrees: the margin)
    holes = [silhouette_holes(v0, faces, view.cam) if params.skip_hole_rims else None for view in views]
    holes = [h if h is not None and h.any() else None for h in holes]  # most views of most objects: none

    r, t, b = np.eye(3), np.zeros(3), 0.0
    stats = (np.inf, np.inf, 0, 0.0, 0.0)
    it = 0
    for it in range(1, params.iterations + 1):
        v = v0 @ r.T + t
        fn = n0 @ r.T
        pivot = v.mean(axis=0)
        found = [_contours(v, faces, fn, edges, view, params.min_height) for view in views]
        if sum(len(f[0]) for f in found) == 0:
            break
        outer = _outer(rays, np.concatenate([np.broadcast_to(vw.centre, f[1].shape) for vw, f in zip(views, found)]),
                       np.concatenate([f[2] for f in found]), r, t)
        splits = np.cumsum([len(f[0]) for f in found])[:-1]
        rows, res, px, wts = [], [], [], []
        for view, hole, (_, p, q), keep in zip(views, holes, found, np.split(outer, splits)):
            p, q = p[keep], q[keep]
            if len(p) == 0:
                continue
            pc = p @ view.r.T + view.t
            z = pc[:, 2]
            c = view.cam
            u = c.fx * pc[:, 0] / z + c.cx
            w = c.fy * pc[:, 1] / z + c.cy
            ok = (z > 0) & (u >= 1) & (u <= c.width - 2) & (w >= 1) & (w <= c.height - 2)
            if view.known is not None:
                ok[ok] = view.known[np.rint(w[ok]).astype(int), np.rint(u[ok]).astype(int)]
            if hole is not None:
                ok[ok] = ~hole[np.rint(w[ok]).astype(int), np.rint(u[ok]).astype(int)]
            if not ok.any():
                continue
            p, q, pc, z, u, w = p[ok], q[ok], pc[ok], z[ok], u[ok], w[ok]
            if view.grey is not None:
                qc = q @ view.r.T + view.t
                du, dw = c.fx * qc[:, 0] / qc[:, 2] + c.cx - u, c.fy * qc[:, 1] / qc[:, 2] + c.cy - w
                nd = np.maximum(np.hypot(du, dw), 1e-9)
                con = _contrast(view, u, w, du / nd, dw / nd, params.contrast_px)
                wts.append(con**2 / (con**2 + params.contrast_ref**2))
            else:
                wts.append(np.ones(len(p)))
            sd = bilinear(view.sd, u, w)
            g = bilinear(view.grad, u, w)  # (N, 2) d sd / d (u, v)
            # through the projection: d sd / d p_cam, then d sd / d p (world) (N, 3)
            gc = np.stack([g[:, 0] * c.fx / z, g[:, 1] * c.fy / z,
                           -(g[:, 0] * c.fx * pc[:, 0] + g[:, 1] * c.fy * pc[:, 1]) / z**2], axis=1)
            gw = gc @ view.r
            k = z / c.fx  # metres per pixel at the point
            # d residual / d (omega, tau, b); a rotation omega about the pivot moves p by omega x (p - pivot)
            rows.append(np.c_[np.cross(p - pivot, gw) * k[:, None], gw * k[:, None], -k])
            res.append((sd - b) * k)
            px.append(sd - b)
        if not rows:
            break
        a, e, epx, wt = np.concatenate(rows), np.concatenate(res), np.concatenate(px), np.concatenate(wts)
        sure = wt >= 0.5 if np.mean(wt >= 0.5) > 0.2 else np.ones(len(wt), bool)
        sigma = 1.4826 * float(np.median(np.abs(epx[sure] - np.median(epx[sure]))))
        inl = np.abs(epx) <= max(params.inlier_px, 3 * sigma)
        wi = wt[inl]
        stats = (float(np.sqrt(np.sum(wi * epx[inl] ** 2) / wi.sum())),
                 float(np.sqrt(np.sum(wi * e[inl] ** 2) / wi.sum())), len(e), float(inl.mean()),
                 float(np.sum(wt * (np.abs(epx) <= params.inlier_px)) / wt.sum()))
        ai, ei = a[inl] * np.sqrt(wi)[:, None], e[inl] * np.sqrt(wi)
        nm = ai.T @ ai
        nm += params.damping * np.diag(np.diag(nm)) + 1e-12 * np.eye(7)
        x = np.linalg.solve(nm, -ai.T @ ei)
        dr = Rotation.from_rotvec(x[:3]).as_matrix()
        r = dr @ r
        t = dr @ (t - pivot) + pivot + x[3:6]
        b += float(x[6])
        # rest on z = 0: the height is the support's, not the silhouettes' (their lowest millimetres are not
        # measured), so the fit's own height step is undone; converged when the rest of the step is negligible
        t[2] -= float((v0 @ r.T + t)[:, 2].min())
        if np.linalg.norm(x[:3]) < params.tol_rad and np.linalg.norm(x[3:5]) < params.tol_m:
            break
    ww = np.eye(4)
    ww[:3, :3], ww[:3, 3] = r, t
    moved = float(np.linalg.norm(v0.mean(axis=0) @ r.T + t - v0.mean(axis=0)))
    return SilhouetteFit(world_from_world=ww.tolist(),
                         rotation_deg=float(np.degrees(np.linalg.norm(Rotation.from_matrix(r).as_rotvec()))),
                         translation_mm=moved * 1e3, rms_px=stats[0], rms_mm=stats[1] * 1e3, offset_px=b,
                         points=stats[2], inlier_fraction=stats[3], agree_fraction=stats[4], iterations=it)
