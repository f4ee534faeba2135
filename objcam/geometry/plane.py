"""Robust plane fit to the support's points: RANSAC for the inliers, then least squares (SVD) on them.

The world frame already puts the board at z = 0 (the sfm stage aligns it), so the fit checks that frame (tilt,
offset) and measures how flat the support is (RMS of the inliers); a large RMS says the surface is not a plane.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict


class PlaneFit(BaseModel):
    """normal (3,) unit, pointing +z; d: the plane is {x : normal . x = d} (metres). Residuals in millimetres."""

    model_config = ConfigDict(frozen=True)
    normal: tuple[float, float, float]
    d: float
    n_points: int
    n_inliers: int
    rms_mm: float  # RMS distance of the inliers to the fitted plane
    p95_mm: float  # 95th percentile of the inliers' distances
    tilt_deg: float  # angle between the fitted normal and +z
    offset_mm: float  # signed height of the fitted plane above the origin
    z_rms_mm: float  # RMS of the inliers' z (their distance to the world plane z = 0)

    def deviation_mm(self, radius_m: float) -> float:
        """How far (mm) the fitted plane strays from the world's z = 0 anywhere within ``radius_m`` of the origin
        (its offset plus what its tilt adds at that radius): the check on the world frame."""
        return abs(self.offset_mm) + float(np.tan(np.radians(self.tilt_deg)) * radius_m * 1e3)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances (N,) metres of points (N, 3) to the plane (positive on the normal's side)."""
        return np.asarray(points, float) @ np.asarray(self.normal) - self.d


def _lsq_plane(p: np.ndarray) -> tuple[np.ndarray, float]:
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2] if vt[2, 2] >= 0 else -vt[2]
    return n, float(n @ c)


def fit_plane(points: np.ndarray, threshold: float = 1e-3, iterations: int = 500, seed: int = 0) -> PlaneFit:
    """RANSAC (``iterations`` random triples, inliers within ``threshold`` metres), then a least-squares refit
    on the inliers, repeated once with the refined plane's inliers.

    points: (N, 3) world metres, N >= 3. Raises ValueError when fewer than 3 points are given.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3:
        raise ValueError("a plane needs at least 3 points")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(p), size=(iterations, 3))
    a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    n, a = n[ok] / norm[ok, None], a[ok]
    if len(n) == 0:  # every triple degenerate (collinear points): fall back to least squares
        best = np.ones(len(p), bool)
    else:
        d = np.einsum("ij,ij->i", n, a)
        # (iterations, N) distances in chunks: memory stays small for large point sets
        counts = np.zeros(len(n), dtype=np.int64)
        for s in range(0, len(n), 64):
            counts[s:s + 64] = (np.abs(p @ n[s:s + 64].T - d[s:s + 64]) < threshold).sum(axis=0)
        k = int(np.argmax(counts))
        best = np.abs(p @ n[k] - d[k]) < threshold
    for _ in range(2):
        normal, dd = _lsq_plane(p[best])
        best = np.abs(p @ normal - dd) < threshold
        if best.sum() < 3:
            best = np.ones(len(p), bool)
    normal, dd = _lsq_plane(p[best])
    res = np.abs(p[best] @ normal - dd)
    return PlaneFit(normal=tuple(float(x) for x in normal), d=dd, n_points=len(p), n_inliers=int(best.sum()),
                    rms_mm=float(np.sqrt(np.mean(res**2)) * 1e3), p95_mm=float(np.percentile(res, 95) * 1e3),
                    tilt_deg=float(np.degrees(np.arccos(np.clip(normal[2], -1, 1)))), offset_mm=float(dd / normal[2] * 1e3),
                    z_rms_mm=float(np.sqrt(np.mean(p[best, 2] ** 2)) * 1e3))


def triangulate(cams: list, uv: list[np.ndarray]) -> np.ndarray:
    """Linear (DLT) triangulation of one point seen in several views: cams (objcam Camera), uv [(2,) pixels].
    Returns (3,) world metres."""
    rows = []
    for cam, (u, v) in zip(cams, uv):
        cw = np.linalg.inv(cam.matrix)
        p = cam.K @ cw[:3]  # 3x4 projection
        rows += [u * p[2] - p[0], v * p[2] - p[1]]
    a = np.asarray(rows)
    _, _, vt = np.linalg.svd(a)
    x = vt[-1]
    return x[:3] / x[3]


def board_corner_points(png_paths: list, cams: list, spec) -> np.ndarray:
    """The board's ChArUco corners, detected in the views' display images and triangulated from every view that
    sees them (>= 2): (K, 3) world metres. They measure where the photographed board really is."""
    from objcam.sfm.board import detect_file

    seen: dict[int, list[tuple[object, np.ndarray]]] = {}
    for path, cam in zip(png_paths, cams):
        ids, uv = detect_file(path, spec)
        for i, p in zip(ids, uv):
            seen.setdefault(int(i), []).append((cam, p))
    pts = [triangulate([c for c, _ in obs], [p for _, p in obs]) for obs in seen.values() if len(obs) >= 2]
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)
