"""Bundle adjustment with the board held fixed: the final refinement of a board-aligned (world-frame) model.

After ``objcam.sfm.align`` has put the SfM model in the world frame, its cameras are as good as SfM made them, and
SfM saw a nearly planar, weakly textured scene (the board ring, a white sheet, an untextured object). Here every
camera pose, every SfM point and (optionally) the focal lengths are refined jointly on

* the reprojection error of the SfM points (their COLMAP observations), and
* the reprojection error of the board's ChArUco corners, held at their exact world positions,

with a robust (Huber) loss, by Levenberg-Marquardt with analytic Jacobians and a sparse direct solve. The board
fixes the gauge (metric scale, plane z = 0, board axes) and ties every camera to the known geometry, as a
calibration target does.

Camera models: the pinhole models (SIMPLE_PINHOLE, PINHOLE) are refined in pixels; cameras with distortion
(SIMPLE_RADIAL, OPENCV, ...) keep their intrinsics: their observations are undistorted once
(``Camera.cam_from_img``) and fitted with the pinhole part.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from objcam.sfm.board import BoardSpec, board_points_world


@dataclass
class BundleResult:
    n_cameras: int
    n_points: int
    n_sfm_observations: int
    n_board_observations: int
    sfm_rms_px_before: float
    sfm_rms_px_after: float
    board_rms_px_before: float
    board_rms_px_after: float
    iterations: int
    seconds: float

    def metrics(self) -> dict:
        return dict(self.__dict__)


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean((r.reshape(-1, 2) ** 2).sum(1)))) if r.size else float("nan")


def bundle_adjust_with_board(rec, detections: dict[str, tuple[np.ndarray, np.ndarray]], spec: BoardSpec,
                             refine_focal: bool = True, refine_principal_point: bool = False,
                             constant_camera_ids: set[int] | frozenset = frozenset(), huber_px: float = 1.0,
                             sfm_weight: float = 1.0, tie_focal: bool = True, min_images_for_intrinsics: int = 3,
                             max_initial_error_px: float = 4.0, max_iterations: int = 50) -> BundleResult:
    """Refine ``rec`` (already in the world frame, metres) in place; see the module docstring.

    detections: {image name: (corner ids, corners (N, 2) OpenCV pixels)} (``BoardObservations.detections``).
    constant_camera_ids: COLMAP cameras whose intrinsics stay fixed (known intrinsics).
    tie_focal: refine one focal length per camera (fy / fx held), as for square pixels.
    min_images_for_intrinsics: cameras with fewer registered images keep their intrinsics (a lone target image
    constrains its focal length poorly: measured 4 mm off at 320 x 240 when refined, 1.5 mm when held).
    sfm_weight: weight of the SfM observations' squared residuals relative to the board corners'.
    Observations more than ``max_initial_error_px`` off at the start are left out.
    """
    import pycolmap
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve
    from scipy.spatial.transform import Rotation

    t_start = time.perf_counter()
    images = [img for img in rec.images.values() if img.has_pose]
    n_c = len(images)
    img_index = {img.image_id: i for i, img in enumerate(images)}
    R = np.zeros((n_c, 3, 3))
    T = np.zeros((n_c, 3))
    for i, img in enumerate(images):
        m = np.asarray(img.cam_from_world().matrix())
        R[i], T[i] = m[:, :3], m[:, 3]

    # cameras: pinhole intrinsics [fx, fy, cx, cy] (COLMAP pixels) and which of them are free
    cam_ids = sorted({img.camera_id for img in images})
    cam_index = {c: k for k, c in enumerate(cam_ids)}
    img_cam = np.array([cam_index[img.camera_id] for img in images], int)
    K = np.zeros((len(cam_ids), 4))
    free_idx: list[list[int]] = []  # indices into [fx, fy, cx, cy]; SIMPLE models tie fx = fy (index 0 only)
    distorted = []
    for k, c in enumerate(cam_ids):
        cam = rec.cameras[c]
        K[k] = [cam.focal_length_x, cam.focal_length_y, cam.principal_point_x, cam.principal_point_y]
        name = cam.model.name
        is_pinhole = name in ("SIMPLE_PINHOLE", "PINHOLE")
        distorted.append(not is_pinhole)
        idx = []
        n_imgs = sum(1 for img in images if img.camera_id == c)
        if is_pinhole and c not in constant_camera_ids and n_imgs >= min_images_for_intrinsics:
            if refine_focal:
                idx += [0] if (name == "SIMPLE_PINHOLE" or tie_focal) else [0, 1]
            if refine_principal_point:
                idx += [2, 3]
        free_idx.append(idx)
    n_intr = [len(f) for f in free_idx]
    simple = [rec.cameras[c].model.name == "SIMPLE_PINHOLE" for c in cam_ids]
    tied = [sm or tie_focal for sm in simple]  # one focal parameter; fy / fx stays as it is
    aspect = K[:, 1] / K[:, 0]

    def undistort(cam_k: int, uv: np.ndarray) -> np.ndarray:
        """COLMAP pixels -> the pinhole pixels of the same ray (identity for pinhole models)."""
        if not distorted[cam_k]:
            return uv
        n = np.asarray(rec.cameras[cam_ids[cam_k]].cam_from_img(uv), float).reshape(-1, 2)
        return n * K[cam_k, :2] + K[cam_k, 2:]

    # observations: SfM points (free) and board corners (fixed), in COLMAP pixels
    pids = sorted(rec.points3D)
    n_p = len(pids)
    X = np.array([rec.points3D[p].xyz for p in pids], dtype=float).reshape(-1, 3)
    o_cam, o_pt, o_uv = [], [], []
    for j, pid in enumerate(pids):
        for el in rec.points3D[pid].track.elements:
            if el.image_id in img_index:
                o_cam.append(img_index[el.image_id])
                o_pt.append(j)
                o_uv.append(rec.images[el.image_id].points2D[el.point2D_idx].xy)
    world = board_points_world(spec)
    by_name = {img.name: i for i, img in enumerate(images)}
    b_cam, b_X, b_uv = [], [], []
    for name, (ids, corners) in detections.items():
        if name in by_name:
            for kk, uv in zip(ids, corners):
                b_cam.append(by_name[name])
                b_X.append(world[int(kk)])
                b_uv.append(np.asarray(uv, float) + 0.5)
    n_s = len(o_cam)
    cam_of = np.array(o_cam + b_cam, int)
    pt_of = np.array(o_pt + [-1] * len(b_cam), int)  # -1: a fixed board point
    uv = np.array(o_uv + b_uv, float).reshape(-1, 2)
    for k in range(len(cam_ids)):
        s = img_cam[cam_of] == k
        if s.any() and distorted[k]:
            uv[s] = undistort(k, uv[s])
    Xb = np.array(b_X, float).reshape(-1, 3)

    def points(Xs):
        out = np.empty((len(cam_of), 3))
        out[:n_s] = Xs[pt_of[:n_s]]
        out[n_s:] = Xb
        return out

    def residuals(R, T, Xs, K):
        P = points(Xs)
        p = np.einsum("nij,nj->ni", R[cam_of], P) + T[cam_of]
        kk = K[img_cam[cam_of]]
        proj = np.stack([kk[:, 0] * p[:, 0] / p[:, 2] + kk[:, 2], kk[:, 1] * p[:, 1] / p[:, 2] + kk[:, 3]], 1)
        return proj - uv, p, P

    r0, _, _ = residuals(R, T, X, K)
    e0 = np.linalg.norm(r0, axis=1)
    use = e0 <= max_initial_error_px
    before_s, before_b = _rms(r0[:n_s][use[:n_s]]), _rms(r0[n_s:][use[n_s:]])

    # parameter layout: [cameras 6 n_c (rotation update, translation) | intrinsics | points 3 n_p]
    intr_off = 6 * n_c + np.concatenate([[0], np.cumsum(n_intr)[:-1]]).astype(int)
    n_cam_par = 6 * n_c + sum(n_intr)
    n_par = n_cam_par + 3 * n_p
    obs = np.nonzero(use)[0]
    m = len(obs)
    ci, pj = cam_of[obs], pt_of[obs]
    kc = img_cam[ci]

    def jacobian(R, T, Xs, K):
        _, p, P = residuals(R, T, Xs, K)
        p = p[obs]
        kk = K[kc]
        iz = 1.0 / p[:, 2]
        drdp = np.zeros((m, 2, 3))
        drdp[:, 0, 0] = kk[:, 0] * iz
        drdp[:, 0, 2] = -kk[:, 0] * p[:, 0] * iz * iz
        drdp[:, 1, 1] = kk[:, 1] * iz
        drdp[:, 1, 2] = -kk[:, 1] * p[:, 1] * iz * iz
        RX = np.einsum("nij,nj->ni", R[ci], P[obs])
        J_rot = -np.einsum("nij,njk->nik", drdp, _skew(RX))  # d(exp(w) R X)/dw = -[R X]x
        J_t = drdp
        J_X = np.einsum("nij,njk->nik", drdp, R[ci])
        rows, cols, vals = [], [], []
        base = 2 * np.arange(m)
        for a in range(2):
            for b in range(3):
                rows += [base + a, base + a]
                cols += [6 * ci + b, 6 * ci + 3 + b]
                vals += [J_rot[:, a, b], J_t[:, a, b]]
        sfm = pj >= 0
        for a in range(2):
            for b in range(3):
                rows.append(base[sfm] + a)
                cols.append(n_cam_par + 3 * pj[sfm] + b)
                vals.append(J_X[sfm, a, b])
        # intrinsics: r_u = fx x + cx, r_v = fy y + cy (x = p0/p2)
        xn, yn = p[:, 0] * iz, p[:, 1] * iz
        for k in range(len(cam_ids)):
            s = kc == k
            if not s.any():
                continue
            for q, which in enumerate(free_idx[k]):
                col = np.full(s.sum(), intr_off[k] + q)
                if which == 0 and tied[k]:
                    rows += [base[s], base[s] + 1]
                    cols += [col, col]
                    vals += [xn[s], aspect[k] * yn[s]]
                elif which in (0, 1):
                    rows.append(base[s] + which)
                    cols.append(col)
                    vals.append((xn if which == 0 else yn)[s])
                else:
                    rows.append(base[s] + (which - 2))
                    cols.append(col)
                    vals.append(np.ones(s.sum()))
        J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(2 * m, n_par))
        return J

    prior = np.where(obs < n_s, sfm_weight, 1.0)  # per-observation weight on the squared residual

    def cost_and_weights(r):
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-300))
        c = np.where(e <= huber_px, 0.5 * e * e, huber_px * (e - 0.5 * huber_px))
        return float((prior * c).sum()), prior * w

    def update(R, T, Xs, K, d):
        dc = d[: 6 * n_c].reshape(n_c, 6)
        R2 = Rotation.from_rotvec(dc[:, :3]).as_matrix() @ R
        T2 = T + dc[:, 3:]
        K2 = K.copy()
        for k, idx in enumerate(free_idx):
            for q, which in enumerate(idx):
                K2[k, which] += d[intr_off[k] + q]
                if which == 0 and tied[k]:
                    K2[k, 1] = K2[k, 0] * aspect[k]
        X2 = Xs + d[n_cam_par:].reshape(n_p, 3)
        return R2, T2, X2, K2

    lam = 1e-3
    r_all, _, _ = residuals(R, T, X, K)
    cost, w = cost_and_weights(r_all[obs])
    it = 0
    for it in range(1, max_iterations + 1):
        J = jacobian(R, T, X, K)
        W = sp.diags(np.repeat(w, 2))
        JtW = J.T @ W
        H = (JtW @ J).tocsc()
        g = JtW @ r_all[obs].ravel()
        diag = H.diagonal()
        diag = np.where(diag > 0, diag, 1.0)
        improved = False
        for _ in range(10):
            A = H + sp.diags(lam * diag)
            d = -spsolve(A.tocsc(), g)
            if not np.all(np.isfinite(d)):
                lam *= 10
                continue
            R2, T2, X2, K2 = update(R, T, X, K, d)
            r2, _, _ = residuals(R2, T2, X2, K2)
            c2, w2 = cost_and_weights(r2[obs])
            if c2 < cost:
                R, T, X, K, r_all, w = R2, T2, X2, K2, r2, w2
                rel = (cost - c2) / max(cost, 1e-300)
                cost = c2
                lam = max(lam / 10, 1e-9)
                improved = True
                break
            lam *= 10
        if not improved or rel < 1e-4:  # the IRLS tail (Huber weights) creeps on for little gain
            break

    for i, img in enumerate(images):
        rec.frames[img.frame_id].set_cam_from_world(img.camera_id,
                                                    pycolmap.Rigid3d(np.hstack([R[i], T[i][:, None]])))
    for j, pid in enumerate(pids):
        rec.points3D[pid].xyz = X[j]
    for k, c in enumerate(cam_ids):
        if free_idx[k]:
            cam = rec.cameras[c]
            params = np.asarray(cam.params, float).copy()
            if simple[k]:
                params[0] = K[k, 0]
                params[1:3] = K[k, 2:]
            else:
                params[:4] = K[k]
            cam.params = params
    r1 = r_all
    return BundleResult(n_cameras=n_c, n_points=n_p, n_sfm_observations=int(use[:n_s].sum()),
                        n_board_observations=int(use[n_s:].sum()), sfm_rms_px_before=before_s,
                        sfm_rms_px_after=_rms(r1[:n_s][use[:n_s]]), board_rms_px_before=before_b,
                        board_rms_px_after=_rms(r1[n_s:][use[n_s:]]), iterations=it,
                        seconds=round(time.perf_counter() - t_start, 2))
