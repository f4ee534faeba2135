"""The world frame from the board: SfM model -> metres, board plane z = 0, board axes (data_layout.md).

1. Detect the ChArUco corners in every registered image (``objcam.sfm.board.detect``).
2. Triangulate each corner from the SfM poses (multi-view DLT, then Gauss-Newton on the reprojection error, with
   outlier views dropped): corner positions in the SfM frame.
3. Fit the similarity SfM -> world to the corners' known world positions (:func:`umeyama`, closed form; coplanar
   points are fine), then refine its 7 parameters on the reprojection error of the known board corners through
   the SfM cameras (the board's geometry is exact, the triangulation is not).
4. Apply it to the reconstruction (``sparse/0``, COLMAP binary, metres) and convert the poses to objcam Cameras
   (OpenCV convention: objcam cx = COLMAP cx - 0.5).

:func:`pnp_camera` is the per-image alternative: the pose from the board alone (``cv2.solvePnP``) with known
intrinsics; it cross-checks (or replaces) the SfM pose of a target image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from objcam.camera import Camera
from objcam.errors import InputError
from objcam.sfm.board import BoardSpec, board_points_world, detect, read_display_image, world_points_array


# ------------------------------------------------------------------------------------------------ similarity


@dataclass(frozen=True)
class Similarity:
    """dst = scale * R @ src + t."""

    scale: float
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points, float) @ self.R.T + self.t

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.R
        m[:3, 3] = self.t
        return m

    def inverse(self) -> "Similarity":
        return Similarity(1.0 / self.scale, self.R.T, -self.R.T @ self.t / self.scale)

    def to_pycolmap(self):
        import pycolmap

        return pycolmap.Sim3d(np.hstack([self.scale * self.R, self.t[:, None]]))


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity (Umeyama 1991) with dst ~ scale R src + t, for (N, 3) point sets, N >= 3 not
    collinear. Coplanar points are fine (the reflection ambiguity is resolved towards a proper rotation)."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError("umeyama needs two (N, 3) arrays with N >= 3")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    if d[1] < 1e-12 * max(d[0], 1e-300):
        raise ValueError("umeyama: the points are collinear")
    s_ = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_[2] = -1.0
    R = u @ np.diag(s_) @ vt
    scale = float((d * s_).sum() / var_s) if with_scale else 1.0
    t = mu_d - scale * R @ mu_s
    return Similarity(scale, R, t)


def _rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(r).as_matrix()


def _matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


# -------------------------------------------------------------------------------------------- cameras/poses


def _pose_matrix(image) -> np.ndarray:
    """(4, 4) cam_from_world of a pycolmap Image (``cam_from_world`` is a method in pycolmap 4)."""
    cfw = image.cam_from_world
    cfw = cfw() if callable(cfw) else cfw
    m = np.eye(4)
    m[:3, :4] = np.asarray(cfw.matrix())
    return m


def _pinhole_params(cam) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a COLMAP camera in COLMAP's pixel convention."""
    return float(cam.focal_length_x), float(cam.focal_length_y), float(cam.principal_point_x), \
        float(cam.principal_point_y)


def distortion_params(cam) -> list[float]:
    """The extra (distortion) parameters of a COLMAP camera ([] for pinhole models)."""
    p = np.asarray(cam.params)
    idx = list(cam.extra_params_idxs())
    return [float(p[i]) for i in idx]


def objcam_camera(cam, cam_from_world: np.ndarray, sim: Similarity | None = None) -> Camera:
    """An objcam Camera from a COLMAP camera (pinhole part; see :func:`distortion_params`) and its (3|4, 4)
    ``cam_from_world`` in the SfM frame; ``sim`` (SfM -> world) makes it metric and world-framed.

    With world = s R x + t and x_cam = R_c x + t_c (SfM units), the metric camera frame is s x_cam, so
    cam_from_world = [R_c R^T | s t_c - R_c R^T t].
    """
    m = np.eye(4)
    m[: np.shape(cam_from_world)[0]] = np.asarray(cam_from_world, float)
    Rc, tc = m[:3, :3], m[:3, 3]
    if sim is not None:
        Rn = Rc @ sim.R.T
        tn = sim.scale * tc - Rn @ sim.t
        Rc, tc = Rn, tn
    wfc = np.eye(4)
    wfc[:3, :3] = Rc.T
    wfc[:3, 3] = -Rc.T @ tc
    fx, fy, cx, cy = _pinhole_params(cam)
    return Camera(width=int(cam.width), height=int(cam.height), fx=fx, fy=fy, cx=cx - 0.5, cy=cy - 0.5,
                  world_from_camera=wfc.tolist())


def camera_difference(a: Camera, b: Camera) -> tuple[float, float]:
    """(centre distance in metres, rotation angle between the two orientations in degrees)."""
    d = float(np.linalg.norm(a.centre - b.centre))
    r = a.matrix[:3, :3].T @ b.matrix[:3, :3]
    ang = math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1, 1))))
    return d, ang


# --------------------------------------------------------------------------------------------- triangulation


@dataclass
class BoardObservations:
    """Detected board corners per registered image: {image name: (ids (N,), corners (N, 2) OpenCV pixels)}."""

    detections: dict[str, tuple[np.ndarray, np.ndarray]]
    images_searched: list[str]

    @property
    def n_views_with_board(self) -> int:
        return sum(1 for ids, _ in self.detections.values() if len(ids) >= 4)


def detect_images(image_dir: str | Path, names: list[str], spec: BoardSpec) -> BoardObservations:
    """Detect the board in the images ``names`` (relative to ``image_dir``)."""
    det: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name in names:
        ids, corners = detect(read_display_image(Path(image_dir) / name), spec)
        if len(ids):
            det[name] = (ids, corners)
    return BoardObservations(det, sorted(names))


def detect_in_reconstruction(rec, image_dir: str | Path, spec: BoardSpec) -> BoardObservations:
    """Detect the board in every registered image of ``rec`` (files under ``image_dir``)."""
    return detect_images(image_dir, [img.name for img in rec.images.values() if img.has_pose], spec)


def registered_subset(obs: BoardObservations, rec) -> BoardObservations:
    """``obs`` restricted to the images registered in ``rec``."""
    reg = {img.name for img in rec.images.values() if img.has_pose}
    return BoardObservations({k: v for k, v in obs.detections.items() if k in reg},
                             sorted(n for n in obs.images_searched if n in reg))


@dataclass
class Calibration:
    """Intrinsics from the board (Zhang's method over the views, ``cv2.calibrateCamera``)."""

    camera: Camera  # intrinsics (OpenCV convention); identity pose
    distortion: list[float]  # OpenCV k1, k2, p1, p2, k3 (zeros unless estimated)
    rms_px: float
    n_views: int
    n_corners: int


def calibrate_intrinsics(obs: BoardObservations, names: list[str], spec: BoardSpec, width: int, height: int,
                         radial: bool = False, square_pixels: bool = True,
                         min_corners: int = 8) -> Calibration | None:
    """The focal length (and with ``radial`` k1) from the board corners in the images ``names`` of one camera;
    the principal point is held at the image centre, no tangential distortion, square pixels (fx = fy; without
    ``square_pixels`` fx and fy are separate when three or more images have the board: measured on 10 ring views
    at 320 x 240 that doubles the focal error, 0.9% and 1.6% vs 0.3%). One view suffices. None when no image has
    ``min_corners`` corners."""
    import cv2

    objp, imgp = [], []
    for n in names:
        if n in obs.detections and len(obs.detections[n][0]) >= min_corners:
            ids, uv = obs.detections[n]
            objp.append(world_points_array(spec, ids).astype(np.float32))
            imgp.append(uv.astype(np.float32).reshape(-1, 1, 2))
    if not objp:
        return None
    f0 = 1.2 * max(width, height)
    K0 = np.array([[f0, 0, (width - 1) / 2], [0, f0, (height - 1) / 2], [0, 0, 1]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_ZERO_TANGENT_DIST
             | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    if not radial:
        flags |= cv2.CALIB_FIX_K1
    if square_pixels or len(objp) < 3:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-12)
    n_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # with OpenCV's threads the result varies run to run (fx in its 11th digit)
    try:
        rms, K, dist, _, _ = cv2.calibrateCamera(objp, imgp, (width, height), K0, np.zeros(5), flags=flags,
                                                 criteria=crit)
    finally:
        cv2.setNumThreads(n_threads)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        return None
    cam = Camera(width=width, height=height, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]),
                 cy=float(K[1, 2]), world_from_camera=np.eye(4).tolist())
    return Calibration(cam, [float(x) for x in np.ravel(dist)[:5]], float(rms), len(objp),
                       int(sum(len(o) for o in objp)))


def _normalised(cam, uv_opencv: np.ndarray) -> np.ndarray:
    """Undistorted normalised image coordinates (N, 2) of OpenCV pixel coordinates (COLMAP: +0.5)."""
    pts = np.asarray(uv_opencv, float).reshape(-1, 2) + 0.5
    return np.asarray(cam.cam_from_img(pts), float).reshape(-1, 2)


def _triangulate_point(Ps: np.ndarray, xs: np.ndarray, w: np.ndarray, iters: int = 10) -> np.ndarray:
    """One point from (K, 3, 4) normalised projections and (K, 2) normalised observations, weights w (K,)
    (focal lengths, so residuals are ~pixels): DLT then Gauss-Newton. NaNs where the rays fix no point (they
    meet at infinity or pass through the point from one centre: a degenerate or collapsed model)."""
    nan = np.full(3, np.nan)
    A = np.concatenate([xs[:, :1] * Ps[:, 2] - Ps[:, 0], xs[:, 1:2] * Ps[:, 2] - Ps[:, 1]], axis=0)
    A *= np.concatenate([w, w])[:, None]
    if not np.all(np.isfinite(A)):
        return nan
    _, _, vt = np.linalg.svd(A)
    if abs(vt[-1, 3]) < 1e-12 * np.linalg.norm(vt[-1, :3]):
        return nan
    X = vt[-1, :3] / vt[-1, 3]
    for _ in range(iters):
        p = np.einsum("kij,j->ki", Ps[:, :, :3], X) + Ps[:, :, 3]
        if not np.all(np.abs(p[:, 2]) > 0):
            return nan
        r = (p[:, :2] / p[:, 2:3] - xs) * w[:, None]
        J = np.zeros((len(Ps), 2, 3))
        inv = 1.0 / p[:, 2]
        J[:, 0] = (Ps[:, 0, :3] - (p[:, 0] * inv)[:, None] * Ps[:, 2, :3]) * inv[:, None]
        J[:, 1] = (Ps[:, 1, :3] - (p[:, 1] * inv)[:, None] * Ps[:, 2, :3]) * inv[:, None]
        J *= w[:, None, None]
        Jf, rf = J.reshape(-1, 3), r.reshape(-1)
        if not np.all(np.isfinite(rf)):
            return nan
        step = np.linalg.lstsq(Jf, -rf, rcond=None)[0]
        X = X + step
        if np.linalg.norm(step) < 1e-12 * (1 + np.linalg.norm(X)):
            break
    return X


def _reproj_px(Ps, xs, w, X) -> np.ndarray:
    p = np.einsum("kij,j->ki", Ps[:, :, :3], X) + Ps[:, :, 3]
    return np.linalg.norm((p[:, :2] / p[:, 2:3] - xs) * w[:, None], axis=1)


#: Corners whose views' rays meet at less than this are not triangulated: two photos from one tripod (another
#: illumination, the same framing) saw corners no view did, and their 0-degree "triangulation" put one 1.7 m off
#: (board residual 83 mm RMS, graded red). At 5 deg a corner 0.5 m away seen to 0.3 px by a 600 px focal length is
#: placed to ~3 mm in depth, and the similarity is refined on the corners' reprojection, not on their depth.
MIN_TRIANGULATION_DEG = 5.0


def triangulate_corners(rec, obs: BoardObservations, max_error_px: float = 2.0, min_views: int = 2,
                        min_angle_deg: float = MIN_TRIANGULATION_DEG) -> dict[int, tuple[np.ndarray, int, float]]:
    """Board corner positions in the SfM frame: {corner id: (xyz, number of views used, RMS reprojection px)}.

    Observations more than ``max_error_px`` (or 4x the median) off are dropped and the point re-solved; corners
    seen in fewer than ``min_views`` views, in front of no camera, or whose rays meet at less than
    ``min_angle_deg`` (the widest angle between two of its views' rays: its depth is then barely determined) are
    left out."""
    by_name = {img.name: img for img in rec.images.values()}
    per_id: dict[int, list[tuple[np.ndarray, np.ndarray, float]]] = {}
    for name, (ids, corners) in obs.detections.items():
        img = by_name[name]
        cam = rec.cameras[img.camera_id]
        P = _pose_matrix(img)[:3]
        xs = _normalised(cam, corners)
        f = 0.5 * (cam.focal_length_x + cam.focal_length_y)
        for k, x in zip(ids, xs):
            per_id.setdefault(int(k), []).append((P, x, f))
    out = {}
    for k, lst in per_id.items():
        if len(lst) < min_views:
            continue
        Ps = np.stack([a for a, _, _ in lst])
        xs = np.stack([b for _, b, _ in lst])
        w = np.array([c for _, _, c in lst])
        X = _triangulate_point(Ps, xs, w)
        if not np.all(np.isfinite(X)):
            continue
        for _ in range(2):
            e = _reproj_px(Ps, xs, w, X)
            keep = e <= max(min(max_error_px, 4 * np.median(e)), 0.25)
            if keep.all() or keep.sum() < min_views:
                break
            Ps, xs, w = Ps[keep], xs[keep], w[keep]
            X = _triangulate_point(Ps, xs, w)
        e = _reproj_px(Ps, xs, w, X)
        depth = np.einsum("kj,j->k", Ps[:, 2, :3], X) + Ps[:, 2, 3]
        if len(Ps) < min_views or not np.all(np.isfinite(e)) or np.any(depth <= 0) or \
                np.sqrt(np.mean(e**2)) > max_error_px:
            continue
        if _widest_ray_angle_deg(Ps, X) < min_angle_deg:
            continue
        out[k] = (X, len(Ps), float(np.sqrt(np.mean(e**2))))
    return out


def _widest_ray_angle_deg(Ps: np.ndarray, X: np.ndarray) -> float:
    """The widest angle, in degrees, between the rays from the centres of cameras ``Ps`` (K, 3, 4) to ``X``."""
    centres = -np.einsum("kji,kj->ki", Ps[:, :, :3], Ps[:, :, 3])  # -R^T t
    rays = X - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0))))


# ---------------------------------------------------------------------------------------------- alignment


@dataclass
class BoardAlignment:
    """The similarity SfM -> world and how well the board fits it."""

    sim: Similarity
    n_corners: int  # triangulated board corners used
    n_views_with_board: int
    n_observations: int  # corner detections used in the refinement
    corner_rms_mm: float  # RMS distance of triangulated corners to their board positions, after alignment
    corner_max_mm: float
    plane_rms_mm: float  # RMS z of the triangulated corners (out of the board plane)
    inplane_rms_mm: float  # RMS in-plane (x, y) distance
    reprojection_rms_px: float  # board corners (known world positions) through the aligned SfM cameras
    scale_m_per_unit: float
    per_corner: dict[int, dict] = field(default_factory=dict)

    def metrics(self) -> dict:
        return {"n_corners": self.n_corners, "n_views_with_board": self.n_views_with_board,
                "n_observations": self.n_observations, "corner_rms_mm": self.corner_rms_mm,
                "corner_max_mm": self.corner_max_mm, "plane_rms_mm": self.plane_rms_mm,
                "inplane_rms_mm": self.inplane_rms_mm, "reprojection_rms_px": self.reprojection_rms_px,
                "scale_m_per_unit": self.scale_m_per_unit, "sim_matrix": self.sim.matrix.tolist()}


def _refine_similarity(sim: Similarity, rec, obs: BoardObservations, spec: BoardSpec,
                       max_error_px: float) -> tuple[Similarity, int, float]:
    """Refine the 7 similarity parameters on the reprojection error of the known board corners through the SfM
    cameras (robust: soft-L1 at 1 px). Returns (similarity, observations used, RMS px of the inliers)."""
    from scipy.optimize import least_squares

    by_name = {img.name: img for img in rec.images.values()}
    world = board_points_world(spec)
    Ps, xs, ws, Xw = [], [], [], []
    for name, (ids, corners) in obs.detections.items():
        img = by_name[name]
        cam = rec.cameras[img.camera_id]
        P = _pose_matrix(img)[:3]
        f = 0.5 * (cam.focal_length_x + cam.focal_length_y)
        for k, x in zip(ids, _normalised(cam, corners)):
            Ps.append(P)
            xs.append(x)
            ws.append(f)
            Xw.append(world[int(k)])
    Ps, xs, ws, Xw = np.array(Ps), np.array(xs), np.array(ws), np.array(Xw)

    def unpack(v):
        return Similarity(float(np.exp(v[0])), _rotvec_to_matrix(v[1:4]), v[4:7])

    def resid(v, Ps, xs, ws, Xw):
        inv = unpack(v).inverse()
        Xs = inv.apply(Xw)  # world -> SfM
        p = np.einsum("kij,kj->ki", Ps[:, :, :3], Xs) + Ps[:, :, 3]
        return ((p[:, :2] / p[:, 2:3] - xs) * ws[:, None]).ravel()

    v0 = np.concatenate([[math.log(sim.scale)], _matrix_to_rotvec(sim.R), sim.t])
    r0 = np.linalg.norm(resid(v0, Ps, xs, ws, Xw).reshape(-1, 2), axis=1)
    keep = r0 <= max(max_error_px, 4 * np.median(r0))
    sol = least_squares(resid, v0, args=(Ps[keep], xs[keep], ws[keep], Xw[keep]), loss="soft_l1", f_scale=1.0,
                        x_scale="jac")
    r = np.linalg.norm(resid(sol.x, Ps, xs, ws, Xw).reshape(-1, 2), axis=1)
    inl = r <= max_error_px
    return unpack(sol.x), int(inl.sum()), float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")


def align_to_board(rec, image_dir: str | Path, spec: BoardSpec, obs: BoardObservations | None = None,
                   refine: bool = True, max_error_px: float = 2.0,
                   error_path: str | Path | None = None) -> BoardAlignment:
    """The similarity SfM -> world from the board (see the module docstring).

    Raises InputError (naming ``error_path``, default ``image_dir``) when the board is found in fewer than two
    registered images or fewer than six of its corners can be triangulated.
    """
    obs = obs if obs is not None else detect_in_reconstruction(rec, image_dir, spec)
    where = error_path if error_path is not None else image_dir
    n_views = obs.n_views_with_board
    if n_views < 2:
        raise InputError(f"the ChArUco board was found in {n_views} of the {len(obs.images_searched)} registered "
                         "images", where,
                         f"keep the printed board ({spec.squares_x} x {spec.squares_y} squares of "
                         f"{spec.square_length * 1000:g} mm, {spec.dictionary}) flat, in focus and in view in "
                         "most photos, and check the board settings match the print")
    tri = triangulate_corners(rec, obs, max_error_px=max_error_px)
    if len(tri) < 6:
        raise InputError(f"only {len(tri)} board corners could be triangulated from {n_views} views", where,
                         "take more views with the whole printed ring of the board in view")
    ids = np.array(sorted(tri))
    src = np.array([tri[k][0] for k in ids])
    dst = world_points_array(spec, ids)
    sim = umeyama(src, dst)
    n_obs, rms_px = sum(len(i) for i, _ in obs.detections.values()), float("nan")
    if refine:
        sim, n_obs, rms_px = _refine_similarity(sim, rec, obs, spec, max_error_px)
    res = sim.apply(src) - dst
    dist = np.linalg.norm(res, axis=1)
    per_corner = {int(k): {"views": tri[k][1], "reproj_px": tri[k][2], "error_mm": float(d * 1000)}
                  for k, d in zip(ids, dist)}
    return BoardAlignment(
        sim=sim, n_corners=len(ids), n_views_with_board=n_views, n_observations=n_obs,
        corner_rms_mm=float(np.sqrt(np.mean(dist**2)) * 1000), corner_max_mm=float(dist.max() * 1000),
        plane_rms_mm=float(np.sqrt(np.mean(res[:, 2] ** 2)) * 1000),
        inplane_rms_mm=float(np.sqrt(np.mean((res[:, :2] ** 2).sum(1))) * 1000),
        reprojection_rms_px=rms_px, scale_m_per_unit=sim.scale, per_corner=per_corner)


def apply_alignment(rec, sim: Similarity, out_dir: str | Path | None = None):
    """Transform ``rec`` in place into the world frame (metres) and, with ``out_dir``, write it there (COLMAP
    binary: cameras.bin, images.bin, points3D.bin, ...). Returns ``rec``."""
    rec.transform(sim.to_pycolmap())
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        rec.write(str(out_dir))
    return rec


def cameras_from_reconstruction(rec, sim: Similarity | None = None) -> dict[str, Camera]:
    """{image name: objcam Camera} for every registered image; ``sim`` maps the model's frame to world (leave it
    None for a model already transformed by :func:`apply_alignment`)."""
    out = {}
    for img in rec.images.values():
        if img.has_pose:
            out[img.name] = objcam_camera(rec.cameras[img.camera_id], _pose_matrix(img), sim)
    return out


# ----------------------------------------------------------------------------------------------------- PnP


@dataclass
class PnPResult:
    camera: Camera
    n_corners: int
    rms_px: float


def _collinear(xy: np.ndarray, ratio: float = 0.05) -> bool:
    """Whether board points ``xy`` (N, 2) lie (nearly) on one line: their spread across the principal direction is
    under ``ratio`` of the spread along it (a corner grid's single row or column: 0)."""
    s = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    return bool(s[0] == 0 or s[-1] < ratio * s[0])


def pnp_camera(image: np.ndarray | str | Path, spec: BoardSpec, intrinsics: Camera,
               detection: tuple[np.ndarray, np.ndarray] | None = None) -> PnPResult | None:
    """The camera pose from the board alone: ``cv2.solvePnP`` (IPPE for the planar board, then Levenberg-Marquardt,
    with corners > 2 px off dropped) given ``intrinsics`` (fx, fy, cx, cy, size; its pose is ignored).
    None when fewer than 6 corners are found, when they lie on one line of the board (no pose: IPPE returned NaN
    for 6 corners along one edge, seen from 25 deg up), or when the solve does not converge."""
    import cv2

    if detection is None:
        img = read_display_image(image) if isinstance(image, (str, Path)) else image
        detection = detect(img, spec)
    ids, uv = detection
    if len(ids) < 6:
        return None
    X = world_points_array(spec, ids)
    if _collinear(X[:, :2]):
        return None
    K = intrinsics.K
    ok, rvec, tvec = cv2.solvePnP(X, uv.reshape(-1, 1, 2), K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        return None
    keep = np.ones(len(ids), bool)
    for _ in range(2):
        rvec, tvec = cv2.solvePnPRefineLM(X[keep], uv[keep].reshape(-1, 1, 2), K, None, rvec, tvec)
        proj = cv2.projectPoints(X, rvec, tvec, K, None)[0].reshape(-1, 2)
        err = np.linalg.norm(proj - uv, axis=1)
        new = err <= 2.0
        if new.sum() < 6 or np.array_equal(new, keep):
            break
        keep = new
    if not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        return None
    R = cv2.Rodrigues(rvec)[0]
    wfc = np.eye(4)
    wfc[:3, :3] = R.T
    wfc[:3, 3] = -R.T @ tvec.ravel()
    cam = Camera(width=intrinsics.width, height=intrinsics.height, fx=intrinsics.fx, fy=intrinsics.fy,
                 cx=intrinsics.cx, cy=intrinsics.cy, world_from_camera=wfc.tolist())
    return PnPResult(cam, int(keep.sum()), float(np.sqrt(np.mean(err[keep] ** 2))))


def pnp_check(cameras: Mapping[str, Camera], obs: BoardObservations, spec: BoardSpec) -> dict[str, dict]:
    """Per image with the board: PnP pose (intrinsics from ``cameras``) vs the given (SfM) pose:
    {name: {"centre_mm", "rotation_deg", "n_corners", "rms_px", "camera": PnP Camera}}."""
    out = {}
    for name, det in obs.detections.items():
        if name not in cameras:
            continue
        r = pnp_camera(None, spec, cameras[name], detection=det)  # type: ignore[arg-type]
        if r is None:
            continue
        d, a = camera_difference(cameras[name], r.camera)
        out[name] = {"centre_mm": d * 1000, "rotation_deg": a, "n_corners": r.n_corners, "rms_px": r.rms_px,
                     "camera": r.camera}
    return out


# ------------------------------------------------------------------------------------ no board: plane + height


def plane_height_frame(points: np.ndarray, centres: np.ndarray, axes: np.ndarray, object_height: float,
                       iterations: int = 400, seed: int = 0) -> tuple[Similarity, dict]:
    """The similarity SfM -> world without a board, from the sparse points (P, 3), the camera centres (C, 3) and
    unit optical axes (C, 3) of the views, all in the SfM frame, and the object's known height (metres):

    1. support plane: RANSAC over point triples (inlier band 0.3% of the median camera distance), least squares
       on the inliers; its normal points towards the cameras (world +z);
    2. origin: the point where the optical axes pass closest (least squares), dropped onto the plane;
    3. world +x: from the origin towards the first camera, in the plane;
    4. scale: the 98th percentile of the heights above the plane of the points within a third of the median
       horizontal camera distance of the origin (the object) becomes ``object_height``.

    Returns (similarity, diagnostics). Raises ValueError (with the reason) when the plane or the object cannot
    be found."""
    pts = np.asarray(points, float)
    C = np.asarray(centres, float)
    A = np.asarray(axes, float)
    if len(pts) < 20 or len(C) < 3:
        raise ValueError(f"too few points ({len(pts)}) or views ({len(C)}) to find the support plane")
    # the look-at point: minimise the distance to every optical axis
    M = np.zeros((3, 3))
    b = np.zeros(3)
    for c, a in zip(C, A):
        P = np.eye(3) - np.outer(a, a)
        M += P
        b += P @ c
    look = np.linalg.solve(M, b)
    dist = float(np.median(np.linalg.norm(C - look, axis=1)))
    thr = 0.003 * dist
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(iterations):
        tri = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        inl = np.abs((pts - tri[0]) @ n) < thr
        if inl.sum() > best_n:
            best, best_n = inl, int(inl.sum())
    if best is None or best_n < 10:
        raise ValueError("no support plane in the sparse points")
    q = pts[best]
    mu = q.mean(axis=0)
    n = np.linalg.svd(q - mu)[2][-1]
    if np.mean((C - mu) @ n) < 0:
        n = -n
    o = look - ((look - mu) @ n) * n
    h = (pts - o) @ n
    horiz = (pts - o) - np.outer(h, n)
    r = np.linalg.norm(horiz, axis=1)
    cam_r = float(np.median(np.linalg.norm((C - o) - np.outer((C - o) @ n, n), axis=1)))
    obj = (r < cam_r / 3) & (h > 3 * thr)
    if obj.sum() < 10:
        raise ValueError(f"only {int(obj.sum())} sparse points on the object above the plane")
    height = float(np.percentile(h[obj], 98))
    x = (C[0] - o) - ((C[0] - o) @ n) * n
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    R = np.stack([x, y, n])  # rows: world axes in SfM coordinates
    s = object_height / height
    sim = Similarity(s, R, -s * R @ o)
    resid = (q - mu) @ n
    return sim, {"plane_inliers": best_n, "plane_rms_mm": float(np.sqrt(np.mean(resid**2)) * s * 1000),
                 "object_points": int(obj.sum()), "object_height_sfm": height, "scale_m_per_unit": s}
