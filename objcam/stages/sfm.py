"""Stage ``sfm``: world-frame, metric cameras for every photo (issue 3).

Applies when the capture has ``[views]``. Runs pycolmap over ingest's view copies together with the targets' and
probes' SfM copies, puts the model in the world frame (board in z = 0, metres; or ``[scale]``), writes:
    sparse/0/                      COLMAP binary model, world frame, metres (readable by COLMAP's tools)
    cameras/views/<stem>.json      objcam Camera JSON matching ingest/views/<stem>.exr's size
    cameras/targets/<name>.json    matching ingest/targets/<name>/image.exr's size
    cameras/probes/<name>.json     matching ingest/probes/<name>/image.exr's size
    points.npz                     xyz (P,3) float64 world metres, rgb (P,3) uint8, error (P,) px, track (P,) int
    report.json                    registered/total, reprojection error, scale/plane residuals, graded checks
Also (for COLMAP's tools and debugging): images/<group>/<name>.png (copies of the images SfM saw, so
``sparse/0`` + ``images/`` is a complete COLMAP project), database.db, sparse_sfm/0 (the mapper's raw model).

World frame. With a ``[board]``: the ChArUco corners fix the similarity (``objcam.sfm.frontend``: board-seeded
SfM, Umeyama + reprojection refinement, bundle adjustment with the board held fixed). With ``[scale]`` only
(no board): the support plane is the dominant plane of the sparse points (RANSAC, then least squares), z up
towards the cameras; the origin is where the views' optical axes pass closest (the object the ring looks at),
dropped onto the plane; x is the direction from there to the first view, in the plane; the scale makes the
object's height (the 98th percentile of the heights of the points above the plane near that axis) equal
``[scale] object_height`` (``objcam.sfm.align.plane_height_frame``).

Target and probe cameras: SfM sees copies downsampled like the views; their intrinsics are scaled to the full
ingest images (u_full = (u_copy + 0.5) * s - 0.5 per axis). Targets shot from one tripod position (same
intrinsics, poses within ``same_position_px`` on the support plane) share one camera, their mean pose
(``objcam.sfm.tripod``), so that the transport builds one A for them and the solve fits them together.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.camera import Camera
from objcam.errors import InputError
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import CaptureManifest, try_load

NAME = "sfm"
DEPS: tuple[str, ...] = ("ingest",)
VERSION = "1"
CODE_DEPS: tuple[str, ...] = ("objcam.sfm",)
APPLIES_WHEN = "the capture has [views]"
#: Targets kept apart but posed within this many times sfm.same_position_px of each other are named in the summary.
NEAR_SEPARATE = 10.0


def applies(capture: Path) -> bool:
    m = try_load(capture)
    return m is not None and m.views is not None


def input_files(capture: Path) -> list[Path]:
    return [Path(capture) / "capture.toml"]  # the photos reach this stage through ingest's key


class Params(BaseModel):
    """The useful knobs of ``objcam.sfm.frontend.FrontendOptions`` (the board comes from capture.toml)."""

    model_config = ConfigDict(extra="forbid")
    intrinsics: Literal["auto", "shared", "separate"] = Field(
        "auto", description="one COLMAP camera for views, targets and probes ('shared': one body and zoom), one "
        "per kind ('separate'), or 'auto': shared when every SfM image has the same size, EXIF camera and EXIF "
        "focal length")
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = Field(
        "PINHOLE", description="COLMAP camera model (ingest has undistorted the images when [camera] distortion "
        "is given, so a pinhole fits)")
    max_num_features: int = Field(8192, ge=256, description="SIFT features per image")
    max_image_size: int = Field(1600, ge=64, description="SIFT on images downscaled to this size")
    num_threads: int = Field(2, ge=1, description="CPU threads")
    min_views: int = Field(6, ge=3, description="fewer views is an error")
    min_registered_fraction: float = Field(0.5, ge=0, le=1, description="fewer registered images is an error")
    seed_from_board: bool = Field(True, description="start SfM from the board's PnP poses")
    bundle: bool = Field(True, description="final bundle adjustment with the board held fixed")
    refine_focal: bool = Field(True, description="refine the focal length in the final bundle adjustment")
    sfm_weight: float = Field(0.1, gt=0, le=1, description="weight of SfM points vs board corners in the final "
                              "bundle adjustment")
    target_pose: Literal["bundle", "pnp"] = Field("bundle", description="target/probe poses from the final "
                                                  "model or from a board-only PnP")
    seed: int = Field(0, ge=0, description="random seed of COLMAP (repeatable runs)")
    same_position_px: float = Field(
        5.0, ge=0, description="targets posed with the same intrinsics and poses that move the support plane's "
        "image by at most this many pixels of the SfM images are one tripod position and share one camera, their "
        "mean pose (objcam.sfm.tripod: SfM posed two shots from one tripod 0.2-1.6 px apart, and only targets of "
        "one camera are solved together); 0: every target keeps its own pose")


def _frontend_options(params: Params, m: CaptureManifest):
    from objcam.sfm.board import BoardSpec
    from objcam.sfm.colmap import SfmOptions
    from objcam.sfm.frontend import FrontendOptions

    sfm = SfmOptions(camera_model=params.camera_model, max_num_features=params.max_num_features,
                     max_image_size=params.max_image_size, num_threads=params.num_threads,
                     min_registered_fraction=params.min_registered_fraction, seed=params.seed)
    return FrontendOptions(board=m.board or BoardSpec(), sfm=sfm, min_views=params.min_views,
                           seed_from_board=params.seed_from_board, bundle=params.bundle,
                           refine_focal=params.refine_focal, sfm_weight=params.sfm_weight,
                           target_pose=params.target_pose, copy_images=True)


def _image_size(path: Path) -> tuple[int, int]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return int(img.shape[1]), int(img.shape[0])


def _camera_of(params: Params, ingest: Path, views: list[Path], extra: dict[str, Path],
               view_recs: list[dict]) -> dict[str, str]:
    """Which groups share the views' COLMAP camera (``Params.intrinsics``)."""
    if params.intrinsics == "separate" or not extra:
        return {}
    vsize = _image_size(views[0])
    same_size = all(_image_size(p) == vsize for p in extra.values())
    # one body at one zoom: the same EXIF camera and focal length (unknown values do not count as different)
    cams = {(r.get("camera"), r.get("focal_length_mm")) for r in view_recs}
    for kind in ("targets", "probes"):
        for d in (ingest / kind).glob("*/merge.json"):
            meta = json.loads(d.read_text())
            cams.add((meta.get("camera"), meta.get("focal_length_mm")))
    bodies = {c for c, _ in cams if c not in (None, "unknown camera")}
    zooms = {f for _, f in cams if f is not None}
    if params.intrinsics == "shared":
        if not same_size:
            raise InputError("sfm.intrinsics=shared but the targets'/probes' SfM copies differ in size from the "
                             "views'", ingest, "use --set sfm.intrinsics=separate (or auto)")
        return {"targets": "views", "probes": "views"}
    same = same_size and len(bodies) <= 1 and len(zooms) <= 1
    return {"targets": "views", "probes": "views"} if same else {}


def _scale_camera(cam: Camera, width: int, height: int) -> Camera:
    """The camera of a copy -> the camera of the full image (OpenCV pixel centres: u_full = (u + 0.5) s - 0.5)."""
    sx, sy = width / cam.width, height / cam.height
    return Camera(width=width, height=height, fx=cam.fx * sx, fy=cam.fy * sy, cx=(cam.cx + 0.5) * sx - 0.5,
                  cy=(cam.cy + 0.5) * sy - 0.5, world_from_camera=cam.world_from_camera)


def _write_points(rec, path: Path) -> int:
    from objcam.image_io import save_npz

    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
    err = np.array([p.error for p in pts], np.float64)
    track = np.array([p.track.length() for p in pts], np.int64)
    save_npz(path, xyz=xyz, rgb=rgb, error=err, track=track)
    return len(pts)


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    import pycolmap

    from objcam.sfm.frontend import estimate_cameras
    from objcam.sfm.report import format_checks
    from objcam.sfm.tripod import merge_same_position, nearest_separate

    capture, out, ingest = inputs.capture, inputs.out, inputs.upstream["ingest"]
    m = CaptureManifest.load(capture)
    view_recs = json.loads((ingest / "views.json").read_text())
    views = [ingest / "views" / f"{r['name']}.png" for r in view_recs]
    # SfM copies under unique names (ingest keeps each as <kind>/<name>/sfm.png)
    staged = out / "inputs"
    extra: dict[str, Path] = {}
    targets: dict[str, Path] = {}
    probes: dict[str, Path] = {}
    for kind, names, dst in (("targets", [t.name for t in m.targets if t.folder], targets),
                             ("probes", [p.name for p in m.probes], probes)):
        for name in names:
            src = ingest / kind / name / "sfm.png"
            p = staged / kind / f"{name}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, p)
            dst[name] = p
            extra[f"{kind}/{name}"] = p
    camera_of = _camera_of(params, ingest, views, extra, view_recs)
    if m.board is None:
        result = _estimate_with_scale(out, views, targets, probes, params, m, camera_of, capture)
    else:
        result = estimate_cameras(out, views, targets=targets, probes=probes,
                                  options=_frontend_options(params, m), camera_of=camera_of,
                                  error_path=capture / m.views.folder)
    shutil.rmtree(staged, ignore_errors=True)  # images/ holds the copies COLMAP's model refers to
    target_cams, positions = merge_same_position(result.targets, params.same_position_px)
    apart = nearest_separate(result.targets, target_cams)

    # targets and probes: cameras at the full ingest image size
    scaled = {}
    for kind, cams in (("targets", target_cams), ("probes", result.probes)):
        for name, cam in cams.items():
            meta = json.loads((ingest / kind / name / "merge.json").read_text())
            full = _scale_camera(cam, int(meta["width"]), int(meta["height"]))
            full.save(out / "cameras" / kind / f"{name}.json")
            scaled[f"{kind}/{name}"] = [full.width, full.height]
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    n_points = _write_points(rec, out / "points.npz")

    report = json.loads((out / "report.json").read_text())
    n_img = len(result.sfm.images)
    n_reg = len(result.sfm.registered)
    grade = result.grade
    red = [c for c in result.checks if c.grade == "red"]
    report.update({"registered": f"{n_reg}/{n_img}", "views_registered": f"{len(result.views)}/{len(views)}",
                   "targets_registered": sorted(result.targets), "probes_registered": sorted(result.probes),
                   "full_size_cameras": scaled, "camera_of": camera_of, "n_points": n_points,
                   "target_positions": positions, "nearest_separate_targets": apart,
                   "world_frame": "board" if m.board is not None else "scale.object_height"})
    from objcam.image_io import atomic_write_text

    atomic_write_text(out / "report.json", json.dumps(report, indent=2))
    if not inputs.quiet:
        print(format_checks(result.checks, color=sys.stderr.isatty()), file=sys.stderr)
    al = result.alignment
    metrics = {
        "grade": grade, "registered": n_reg, "images": n_img, "views": len(views),
        "views_registered": len(result.views), "targets_registered": len(result.targets),
        "probes_registered": len(result.probes),
        "mean_reprojection_px": round(result.sfm.mean_reprojection_error_px, 4),
        "board_corner_rms_mm": al.get("corner_rms_mm"), "board_plane_rms_mm": al.get("plane_rms_mm"),
        "board_reprojection_px": (result.bundle or {}).get("board_rms_px_after", al.get("reprojection_rms_px")),
        "n_points": n_points, "shared_camera": bool(camera_of), "seconds": result.seconds,
        "seeded": result.sfm.seeded,
        "target_positions": len(target_cams) - sum(len(p["targets"]) - 1 for p in positions),
    }
    summary = (f"{n_reg}/{n_img} images registered ({len(result.views)}/{len(views)} views, "
               f"{len(result.targets)} target(s), {len(result.probes)} probe(s)), "
               f"{result.sfm.mean_reprojection_error_px:.2f} px, {n_points} points")
    for p in positions:
        summary += f", {' + '.join(p['targets'])} one position ({p['displacement_px']:.2f} px apart: one camera)"
    if apart is not None and apart["displacement_px"] <= NEAR_SEPARATE * params.same_position_px:
        # near misses: meant as one tripod position? they are solved apart (one A each)
        summary += (f", {' / '.join(apart['targets'])} {apart['displacement_px']:.2f} px apart: separate cameras "
                    f"(sfm.same_position_px={params.same_position_px:g})")
    if result.sfm.seeded == "held":
        summary += ", mapped with the board's poses held (the mapper's adjustment collapsed the seeded model)"
    if al.get("corner_rms_mm") is not None:
        summary += f", board {al['corner_rms_mm']:.2f} mm RMS"
    summary += f"; grade {grade}"
    if red:
        summary += " -- " + "; ".join(f"{c.name}: {c.fix}" for c in red)
    return StageOutputs(metrics=metrics, summary=summary)


def _estimate_with_scale(out: Path, views, targets, probes, params: Params, m: CaptureManifest, camera_of,
                         capture: Path):
    """No board: SfM, then the plane/height world frame (module doc)."""
    from objcam.sfm.frontend import estimate_cameras_without_board

    return estimate_cameras_without_board(out, views, m.scale.object_height, targets=targets, probes=probes,
                                          options=_frontend_options(params, m), camera_of=camera_of,
                                          error_path=capture / m.views.folder)
