"""Stage ``texture``: UVs and a first linear albedo of the support and the object from the views (issue 4).

Applies with ``geometry``. Writes:
    object.npz, support.npz        the geometry stage's meshes with UVs (MeshData.uv): xatlas for the object; the
                                   plane's own planar UVs (objcam.scene.make_plane) over a square patch of
                                   ``support_extent`` around the origin, clamped outside (the paper beyond is
                                   constant), which is distortion-free where xatlas would only cut the square
    albedo_object.exr, albedo_support.exr   linear albedo textures over those UVs (RGB float32, in [0, 1])
    confidence_*.exr, counts_*.exr per-texel confidence in [0, 1] and sample counts (one channel)
    texture.json                   what was baked, how many samples were rejected as occluded/out of frame, the
                                   normalisation and its assumption

Albedo from radiance: a diffuse texel's radiance is albedo x irradiance / pi, and the irradiance (the unknown
envmap, shadows) is not known here. The baked radiance is divided by the radiance of **unshadowed paper over its
known albedo** (per channel): with a board, the paper texels of the known print (``PAPER_ALBEDO``), without one
the brightest robust level of the support (assumed to be ``paper_albedo``); the level is a high percentile, since
shadows only darken. This is exact for unshadowed, upward-facing support; in cast shadows the shadow stays baked
in (it is the same in every view), and on the object the assumption that a texel receives the open plane's
irradiance is wrong for faces turned away from the sky. It is the initial rho of the joint solve, which refines it
knowing the light.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.geometry.bake import BakeParams
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import CaptureManifest

NAME = "texture"
DEPS: tuple[str, ...] = ("ingest", "sfm", "geometry")
VERSION = "1"
APPLIES_WHEN = "the capture has [views]"  # via DEPS: applies wherever sfm does



def input_files(capture: Path) -> list[Path]:
    return [Path(capture) / "capture.toml"]


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    object_resolution: int = Field(512, ge=32, le=8192, description="object atlas side, texels")
    support_px_per_m: float = Field(1000.0, gt=0, description="support texels per metre")
    support_extent: float | None = Field(None, gt=0, description="side of the textured support square, metres; "
                                         "default: the board with its margin, else 6 object heights")
    paper_albedo: float = Field(0.8, gt=0, le=1, description="without a board: the albedo assumed for the "
                                "support's brightest robust level")
    paper_percentile: float = Field(90.0, gt=50, le=100, description="percentile of the paper's radiance taken as "
                                    "unshadowed")
    bake: BakeParams = BakeParams()


def _support_grid(extent: float, n: int) -> np.ndarray:
    """World points (n*n, 3) of the support texel centres (make_plane's UVs: column -> +x, row 0 at +y)."""
    s = (np.arange(n) + 0.5) / n * extent - extent / 2
    yy, xx = np.meshgrid(-s, s, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], 1)


def _board_paper(manifest: CaptureManifest, pts: np.ndarray) -> np.ndarray | None:
    """(N,) bool: support points where the known print is plain paper (None without a board)."""
    if manifest.board is None:
        return None
    from objcam.sfm.board import PAPER_ALBEDO, board_texture

    tex = board_texture(manifest.board, 2000.0)
    n = tex.image.shape[0]
    c = np.floor((pts[:, 0] + tex.extent / 2) * tex.px_per_m).astype(int)
    r = np.floor((tex.extent / 2 - pts[:, 1]) * tex.px_per_m).astype(int)
    inside = (c >= 0) & (c < n) & (r >= 0) & (r < n)
    paper = np.ones(len(pts), bool)  # beyond the print: paper (the capture's support is the sheet)
    # paper only where the whole 3x3 neighbourhood is paper: blurred ink edges are not reference paper
    img = tex.image >= PAPER_ALBEDO - 1e-6
    from scipy.ndimage import binary_erosion

    img = binary_erosion(img, np.ones((9, 9), bool), border_value=1)
    paper[inside] = img[r[inside], c[inside]]
    return paper


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    from objcam.geometry.bake import bake
    from objcam.geometry.raycast import RayScene
    from objcam.geometry.uv import atlas, fill_gutter, rasterize, surface_points
    from objcam.geometry.views import load_views
    from objcam.image_io import atomic_write_text, write_exr
    from objcam.scene import MeshData, make_plane
    from objcam.sfm.board import PAPER_ALBEDO

    manifest = CaptureManifest.load(inputs.capture)
    out, geo = inputs.out, inputs.upstream["geometry"]
    times: dict[str, float] = {}
    t = time.perf_counter()
    views = load_views(inputs.upstream["ingest"], inputs.upstream["sfm"], min_views=1)
    obj = MeshData.load_npz(geo / "object.npz")
    height = float(obj.bbox[1][2] - obj.bbox[0][2])
    if params.support_extent is not None:
        extent = params.support_extent
    elif manifest.board is not None:
        from objcam.sfm.board import board_texture

        extent = board_texture(manifest.board, 1000.0).extent
    else:
        extent = 6.0 * height
    n_sup = max(16, int(round(extent * params.support_px_per_m)))
    support = make_plane(manifest.scene.plane_size, extent)
    times["load"] = time.perf_counter() - t

    t = time.perf_counter()
    obj_uv = atlas(obj, params.object_resolution)
    res = params.object_resolution
    face, bary = rasterize(obj_uv, (res, res))
    times["uv"] = time.perf_counter() - t

    t = time.perf_counter()
    rays = RayScene([obj_uv, support])
    o_pts, o_nrm = surface_points(obj_uv, face, bary)
    s_pts = _support_grid(extent, n_sup)
    s_nrm = np.tile([0.0, 0.0, 1.0], (len(s_pts), 1))
    baked = bake(np.concatenate([o_pts, s_pts]), np.concatenate([o_nrm, s_nrm]), views, rays, params.bake,
                 progress=not inputs.quiet)
    times["bake"] = time.perf_counter() - t

    no = len(o_pts)
    rad_s = baked.radiance[no:]
    seen_s = baked.count[no:] > 0
    paper = _board_paper(manifest, s_pts)
    ref_sel = seen_s & (paper if paper is not None else True)
    if ref_sel.sum() < 16:
        from objcam.errors import InputError

        raise InputError("no view sees enough of the support to normalise the albedo", geo / "support.npz",
                         "photograph the paper around the object")
    level = np.percentile(rad_s[ref_sel], params.paper_percentile, axis=0)  # per channel
    ref_albedo = PAPER_ALBEDO if paper is not None else params.paper_albedo
    k = np.maximum(level / ref_albedo, 1e-12)
    albedo = np.clip(baked.radiance / k, 0.0, 1.0)

    # support images (n_sup x n_sup, row-major like _support_grid)
    a_s = albedo[no:].reshape(n_sup, n_sup, 3)
    seen_img = seen_s.reshape(n_sup, n_sup)
    a_s = fill_gutter(a_s, seen_img)
    write_exr(out / "albedo_support.exr", a_s)
    write_exr(out / "confidence_support.exr", baked.confidence[no:].reshape(n_sup, n_sup))
    write_exr(out / "counts_support.exr", baked.count[no:].reshape(n_sup, n_sup).astype(np.float32))
    # object atlas
    covered = face >= 0
    seen_o = np.zeros((res, res), bool)
    seen_o[covered] = baked.count[:no] > 0
    img = np.zeros((res, res, 3), np.float32)
    img[covered] = albedo[:no]
    conf = np.zeros((res, res), np.float32)
    conf[covered] = baked.confidence[:no]
    cnt = np.zeros((res, res), np.float32)
    cnt[covered] = baked.count[:no]
    if seen_o.any():
        img = fill_gutter(img, seen_o)
    else:
        img[:] = 0.5
    write_exr(out / "albedo_object.exr", img)
    write_exr(out / "confidence_object.exr", conf)
    write_exr(out / "counts_object.exr", cnt)
    obj_uv.save(out / "object.npz")
    support.save(out / "support.npz")

    metrics = {
        "object_texels": int(covered.sum()), "object_texels_seen": int(seen_o.sum()),
        "object_resolution": res, "object_faces": int(len(obj_uv.faces)),
        "support_extent_m": extent, "support_texels": int(n_sup * n_sup), "support_texels_seen": int(seen_s.sum()),
        "median_samples_object": float(np.median(baked.count[:no])) if no else 0.0,
        "median_samples_support": float(np.median(baked.count[no:])),
        "rejected_samples": baked.rejected,
        "normalisation": {"paper_radiance": level.tolist(), "paper_albedo": ref_albedo,
                          "reference": "board paper texels" if paper is not None else "brightest support level",
                          "assumption": "albedo = radiance / (unshadowed paper radiance / paper albedo): exact for "
                                        "unshadowed upward-facing support; cast shadows stay baked in; object "
                                        "texels are assumed to receive the open plane's irradiance"},
        "mean_confidence_object": float(conf[covered].mean()) if covered.any() else 0.0,
        "mean_confidence_support": float(baked.confidence[no:].mean()),
        "seconds": times,
    }
    atomic_write_text(out / "texture.json", json.dumps(metrics, indent=2))
    summary = (f"object atlas {res}^2 ({seen_o.sum():,} texels seen), support {n_sup}^2 over {extent * 100:.0f} cm; "
               f"{len(views)} views, paper level {level.mean():.3g}")
    return StageOutputs(metrics=metrics, summary=summary)
