"""The capture front end, end to end: photos of the object on the printed board -> world-frame objcam cameras.

:func:`estimate_cameras` runs SfM over the views and the target images together (``objcam.sfm.colmap``), puts the
model in the world frame from the board (``objcam.sfm.align``), refines it with the board held fixed
(``objcam.sfm.bundle``), checks every target against a board-only PnP pose, grades the run
(``objcam.sfm.report``) and writes, under ``work_dir``::

    images/views/*, images/targets/*.png,  the images SfM saw (links, or copies with ``copy_images``; HDR
    images/probes/*.png                    targets tonemapped)
    database.db, sparse_sfm/0/             COLMAP database and raw model (arbitrary frame)
    sparse/0/                              the final model: world frame, metres (COLMAP binary)
    cameras/views/<stem>.json              objcam Camera JSON (OpenCV convention)
    cameras/targets/<name>.json
    cameras/probes/<name>.json             chrome-ball photos, posed like the targets
    report.json                            metrics, timings and the graded checks
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Literal, Mapping, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.camera import Camera
from objcam.errors import InputError
from objcam.sfm.board import BoardSpec
from objcam.sfm.colmap import SfmOptions, SfmResult, camera_groups, prepare_images, run_sfm
from objcam.sfm.report import Check, format_checks, grade_checks, worst


class FrontendOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    board: BoardSpec = Field(default_factory=BoardSpec)
    sfm: SfmOptions = Field(default_factory=SfmOptions)
    min_views: int = Field(6, ge=3, description="fewer views is an error")
    seed_from_board: bool = Field(True, description="start SfM from the board's PnP poses (robust on small or "
                                  "weakly textured scenes); else COLMAP's own initialisation")
    fix_board_intrinsics_in_sfm: bool = Field(True, description="hold the board-calibrated intrinsics fixed in "
                                              "COLMAP's mapper (pinhole models)")
    bundle: bool = Field(True, description="final bundle adjustment with the board held fixed")
    sfm_weight: float = Field(0.1, gt=0, le=1, description="weight of SfM observations relative to board corners "
                              "in the final bundle adjustment (SIFT points are less accurate than corners)")
    refine_focal: bool = Field(True, description="refine the focal length (one per camera, fy / fx held) in the "
                               "final bundle adjustment")
    target_pose: Literal["bundle", "pnp"] = Field("bundle", description="target poses from the final model, or "
                                                  "from a board-only PnP with the model's intrinsics")
    copy_images: bool = Field(False, description="copy the images into work_dir/images (a self-contained COLMAP "
                              "project that survives moving the folder) instead of linking them")


class FrontendResult(BaseModel):
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True)
    views: dict[str, Camera]  # by file stem, registered views only
    targets: dict[str, Camera]
    probes: dict[str, Camera] = {}
    sfm: SfmResult
    calibration: dict[str, dict]
    colmap_cameras: dict[str, dict]  # per group: final COLMAP model, params and distortion (the Camera JSONs hold
    # the pinhole part only: with a distortion model, undistort the images, e.g. pycolmap.undistort_images)
    alignment: dict
    bundle: dict | None
    target_pnp: dict[str, dict]
    probe_pnp: dict[str, dict] = {}
    checks: list[Check]
    seconds: dict[str, float]

    @property
    def grade(self) -> str:
        return worst(self.checks)

    def summary(self) -> str:
        return format_checks(self.checks)


def _folder_of(paths: Sequence[Path]) -> Path:
    parents = {Path(p).resolve().parent for p in paths}
    return parents.pop() if len(parents) == 1 else Path(".")


def estimate_cameras(work_dir: str | Path, views: Sequence[str | Path], targets: Mapping[str, str | Path] | None = None,
                     options: FrontendOptions | None = None,
                     intrinsics: Mapping[str, Camera] | None = None,
                     probes: Mapping[str, str | Path] | None = None,
                     camera_of: Mapping[str, str] | None = None,
                     error_path: str | Path | None = None) -> FrontendResult:
    """World-frame cameras of ``views`` (image paths), ``targets`` and ``probes`` ({name: image path}; EXR is
    tonemapped).

    intrinsics: optional known intrinsics per camera group ("views", "targets", "probes"): a Camera whose fx, fy,
    cx, cy are used (held fixed); otherwise SfM estimates them (one camera per camera group).
    camera_of: optional {group: camera group}, e.g. {"targets": "views", "probes": "views"} when one camera body
    and zoom took every photo (one COLMAP camera, images of one size); default: a camera per group.
    error_path: the folder errors name (default: the views' folder), e.g. the capture's photo folder.
    Raises InputError for too few views, SfM registering too few images, or the board not found.
    """
    from objcam.sfm.align import (Calibration, align_to_board, apply_alignment, calibrate_intrinsics,
                                  cameras_from_reconstruction, detect_images, distortion_params, pnp_camera,
                                  pnp_check, registered_subset)
    from objcam.sfm.bundle import bundle_adjust_with_board

    options = options or FrontendOptions()
    work = Path(work_dir)
    views = [Path(v) for v in views]
    targets = {k: Path(v) for k, v in (targets or {}).items()}
    probes = {k: Path(v) for k, v in (probes or {}).items()}
    camera_of = dict(camera_of or {})

    def cam_key(group: str) -> str:
        return camera_of.get(group, group)

    folder = Path(error_path) if error_path is not None else (_folder_of(views) if views else work)
    if len(views) < options.min_views:
        raise InputError(f"only {len(views)} view(s) for structure from motion", folder,
                         f"take at least {options.min_views} (better 20 or more) overlapping photos around the "
                         "object, the board in frame")
    t0 = time.perf_counter()
    seconds: dict[str, float] = {}
    image_dir = work / "images"
    target_files = {}
    groups_in: dict[str, list[Path]] = {"views": views}
    if targets:
        groups_in["targets"] = [targets[k] for k in targets]
    if probes:
        groups_in["probes"] = [probes[k] for k in probes]
    groups = prepare_images(image_dir, groups_in, copy=options.copy_images)
    if targets:
        target_files = dict(zip(targets, groups["targets"]))  # name -> "targets/<stem>.png"
    probe_files = dict(zip(probes, groups["probes"])) if probes else {}
    view_files = dict(zip((v.stem for v in views), groups["views"]))
    seconds["prepare"] = time.perf_counter() - t0

    # the board in every image first: intrinsics for SfM's start, and a clear error before the slow part
    t = time.perf_counter()
    all_obs = detect_images(image_dir, [n for names in groups.values() for n in names], options.board)
    seconds["detect"] = time.perf_counter() - t
    n_view_board = sum(1 for n in groups["views"] if n in all_obs.detections and len(all_obs.detections[n][0]) >= 4)
    if n_view_board < 2:
        raise InputError(f"the ChArUco board was found in {n_view_board} of the {len(views)} views", folder,
                         f"print the board ({options.board.squares_x} x {options.board.squares_y} squares of "
                         f"{options.board.square_length * 1000:g} mm, {options.board.dictionary}; "
                         "objcam.sfm.board.write_board_print) at 100% scale, lay it flat under the object and keep "
                         "its printed ring in frame and in focus; check the board settings match the print")
    calib: dict[str, Calibration] = {}
    initial = {}
    for group, names in camera_groups(groups, camera_of).items():
        if intrinsics and group in intrinsics:
            continue
        size = _image_size(image_dir / names[0])
        for n in names[1:]:
            if _image_size(image_dir / n) != size:
                raise InputError(f"images sharing camera {group!r} differ in size ({names[0]}: {size}, {n}: "
                                 f"{_image_size(image_dir / n)})", folder, "give each image size its own camera")
        c = calibrate_intrinsics(all_obs, names, options.board, size[0], size[1],
                                 radial=options.sfm.camera_model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV"))
        if c is not None:
            calib[group] = c
            initial[group] = (c.camera, c.distortion)
    seed: dict[str, Camera] = {}
    if options.seed_from_board:  # board PnP poses (world frame) to start SfM from
        for group, names in groups.items():
            key = cam_key(group)
            k = intrinsics[key] if intrinsics and key in intrinsics else (
                calib[key].camera if key in calib else None)
            if k is None:
                continue
            for n in names:
                if n in all_obs.detections and len(all_obs.detections[n][0]) >= 8:
                    r = pnp_camera(None, options.board, k, detection=all_obs.detections[n])
                    if r is not None and r.rms_px < 2.0:
                        seed[n] = r.camera
    seconds["calibrate"] = time.perf_counter() - t - seconds["detect"]

    # board-calibrated intrinsics are held fixed in SfM (SIFT on a nearly planar scene pulls the focal length
    # off; measured 2.4% at 320 x 240), the final board bundle adjustment may refine them
    fixed = dict(intrinsics or {})
    if options.fix_board_intrinsics_in_sfm:
        fixed.update({g: c for g, (c, dist) in initial.items() if not any(dist)})
    sfm = run_sfm(work, image_dir, groups, intrinsics=fixed, options=options.sfm, error_path=folder,
                  initial_intrinsics=initial, seed_poses=seed, camera_of=camera_of)
    seconds.update({f"sfm_{k}": v for k, v in sfm.seconds.items()})
    rec = sfm.load()

    t = time.perf_counter()
    obs = registered_subset(all_obs, rec)
    al = align_to_board(rec, image_dir, options.board, obs=obs, error_path=folder)
    apply_alignment(rec, al.sim)
    seconds["align"] = time.perf_counter() - t

    bundle = None
    if options.bundle:
        t = time.perf_counter()
        const = set()
        if intrinsics:  # the user's known intrinsics stay fixed
            for img in rec.images.values():
                if cam_key(img.name.split("/")[0]) in intrinsics:
                    const.add(img.camera_id)
        br = bundle_adjust_with_board(rec, obs.detections, options.board, refine_focal=options.refine_focal,
                                      constant_camera_ids=const, sfm_weight=options.sfm_weight)
        bundle = br.metrics()
        seconds["bundle"] = time.perf_counter() - t
    rec.write(_mk(work / "sparse" / "0"))

    cams = cameras_from_reconstruction(rec)
    colmap_cameras: dict[str, dict] = {}
    for img in rec.images.values():
        c = rec.cameras[img.camera_id]
        colmap_cameras.setdefault(img.name.split("/")[0], {
            "model": c.model.name, "params": [float(x) for x in c.params], "distortion": distortion_params(c)})
    pnp = pnp_check(cams, obs, options.board)
    out_views = {stem: cams[f] for stem, f in view_files.items() if f in cams}
    out_targets: dict[str, Camera] = {}
    target_pnp: dict[str, dict] = {}
    for name, f in target_files.items():
        if f not in cams:
            continue
        out_targets[name] = cams[f]
        if f in pnp:
            r = pnp[f]
            target_pnp[name] = {k: v for k, v in r.items() if k != "camera"}
            if options.target_pose == "pnp":
                out_targets[name] = r["camera"]
    out_probes: dict[str, Camera] = {}
    probe_pnp: dict[str, dict] = {}
    for name, f in probe_files.items():
        if f not in cams:
            continue
        out_probes[name] = cams[f]
        if f in pnp:
            probe_pnp[name] = {k: v for k, v in pnp[f].items() if k != "camera"}
            if options.target_pose == "pnp":
                out_probes[name] = pnp[f]["camera"]
    for sub, cs in (("views", out_views), ("targets", out_targets), ("probes", out_probes)):
        for name, cam in cs.items():
            cam.save(_mk(work / "cameras" / sub) / f"{name}.json")

    view_names = set(view_files.values())
    checks = grade_checks(
        n_views=len(views), views_registered=sum(1 for f in view_names if f in cams),
        targets=list(targets), targets_registered=list(out_targets),
        mean_reprojection_px=sfm.mean_reprojection_error_px,
        views_with_board=sum(1 for n, (ids, _) in obs.detections.items() if n in view_names and len(ids) >= 4),
        board_corner_rms_mm=al.corner_rms_mm, board_plane_rms_mm=al.plane_rms_mm,
        board_reprojection_px=bundle["board_rms_px_after"] if bundle else al.reprojection_rms_px,
        target_pnp=target_pnp, board_square_mm=options.board.square_length * 1000,
        probes=list(probes), probes_registered=list(out_probes), probe_pnp=probe_pnp)
    seconds["total"] = time.perf_counter() - t0
    seconds = {k: round(v, 2) for k, v in seconds.items()}
    calibration = {g: {"fx": c.camera.fx, "fy": c.camera.fy, "distortion": c.distortion, "rms_px": c.rms_px,
                       "n_views": c.n_views, "n_corners": c.n_corners} for g, c in calib.items()}
    result = FrontendResult(views=out_views, targets=out_targets, probes=out_probes, sfm=sfm,
                            calibration=calibration,
                            colmap_cameras=colmap_cameras,
                            alignment=al.metrics(), bundle=bundle,
                            target_pnp=target_pnp, probe_pnp=probe_pnp, checks=checks, seconds=seconds)
    from objcam.image_io import atomic_write_text

    atomic_write_text(work / "report.json", json.dumps(
        {"grade": result.grade, "checks": [c.model_dump() for c in checks], "sfm": sfm.model_dump(),
         "calibration": calibration, "colmap_cameras": colmap_cameras, "alignment": al.metrics(),
         "bundle": bundle, "target_pnp": target_pnp, "probe_pnp": probe_pnp, "seconds": seconds,
         "options": options.model_dump(mode="json")},
        indent=2))
    return result


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("image does not read", path, "give an 8/16-bit PNG, JPEG or TIFF, or a linear EXR")
    return int(img.shape[1]), int(img.shape[0])


def _mk(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


def estimate_cameras_without_board(work_dir: str | Path, views: Sequence[str | Path], object_height: float,
                                   targets: Mapping[str, str | Path] | None = None,
                                   probes: Mapping[str, str | Path] | None = None,
                                   options: FrontendOptions | None = None,
                                   camera_of: Mapping[str, str] | None = None,
                                   error_path: str | Path | None = None) -> FrontendResult:
    """World-frame cameras without a board: SfM (COLMAP's own initialisation and intrinsics), then the support
    plane, the object's place and the metric scale from its known height
    (:func:`objcam.sfm.align.plane_height_frame`). Same outputs as :func:`estimate_cameras` (no board checks;
    a plane-residual and an object-points check instead). InputError when the plane or the object is not found."""
    from objcam.image_io import atomic_write_text
    from objcam.sfm.align import _pose_matrix, apply_alignment, cameras_from_reconstruction, plane_height_frame

    options = options or FrontendOptions()
    work = Path(work_dir)
    views = [Path(v) for v in views]
    folder = Path(error_path) if error_path is not None else (_folder_of(views) if views else work)
    if len(views) < options.min_views:
        raise InputError(f"only {len(views)} view(s) for structure from motion", folder,
                         f"take at least {options.min_views} (better 20 or more) overlapping photos around the object")
    t0 = time.perf_counter()
    groups_in: dict[str, list[Path]] = {"views": views}
    targets = {k: Path(v) for k, v in (targets or {}).items()}
    probes = {k: Path(v) for k, v in (probes or {}).items()}
    if targets:
        groups_in["targets"] = list(targets.values())
    if probes:
        groups_in["probes"] = list(probes.values())
    image_dir = work / "images"
    groups = prepare_images(image_dir, groups_in, copy=options.copy_images)
    sfm = run_sfm(work, image_dir, groups, options=options.sfm, error_path=folder, camera_of=camera_of)
    rec = sfm.load()
    view_names = set(groups["views"])
    reg_views = [img for img in rec.images.values() if img.has_pose and img.name in view_names]
    cw = [np.linalg.inv(_pose_matrix(img)) for img in sorted(reg_views, key=lambda i: i.name)]
    xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    try:
        sim, diag = plane_height_frame(xyz, np.array([m[:3, 3] for m in cw]), np.array([m[:3, 2] for m in cw]),
                                       object_height, seed=options.sfm.seed)
    except ValueError as e:
        raise InputError(f"no metric world frame without a board: {e}", folder,
                         "print the ChArUco board and add [board] to capture.toml; without it the scale rests on "
                         "SfM points on the object and the plane: a textured object on a flat, textured "
                         "surface") from None
    apply_alignment(rec, sim)
    rec.write(_mk(work / "sparse" / "0"))
    cams = cameras_from_reconstruction(rec)
    out: dict[str, dict[str, Camera]] = {"views": {}, "targets": {}, "probes": {}}
    for group, names in groups.items():
        keys = [p.stem for p in groups_in[group]] if group == "views" else list(
            targets if group == "targets" else probes)
        for key, f in zip(keys, names):
            if f in cams:
                out[group][key] = cams[f]
                cams[f].save(_mk(work / "cameras" / group) / f"{key}.json")
    checks = [c for c in grade_checks(
        n_views=len(views), views_registered=len(out["views"]), targets=list(targets),
        targets_registered=list(out["targets"]), mean_reprojection_px=sfm.mean_reprojection_error_px,
        views_with_board=len(out["views"]), board_corner_rms_mm=0.0, board_plane_rms_mm=0.0,
        board_reprojection_px=None, probes=list(probes), probes_registered=list(out["probes"]))
        if not c.name.startswith("board")]
    g = "green" if diag["plane_rms_mm"] < 1.0 else ("yellow" if diag["plane_rms_mm"] < 3.0 else "red")
    checks.append(Check(name="support plane", grade=g, value=f"{diag['plane_rms_mm']:.2f} mm RMS",
                        detail=f"{diag['plane_inliers']} points", fix=None if g == "green" else
                        "the surface under the object is not flat or not textured: use a flat, textured sheet"))
    g = "green" if diag["object_points"] >= 50 else "yellow"
    checks.append(Check(name="object height", grade=g, value=f"{diag['object_points']} points on the object",
                        detail="the metric scale rests on the highest points found on the object",
                        fix=None if g == "green" else "few points on the object make the scale uncertain: print "
                        "the board for a reliable scale"))
    colmap_cameras = {}
    for img in rec.images.values():
        c = rec.cameras[img.camera_id]
        colmap_cameras.setdefault(img.name.split("/")[0], {"model": c.model.name,
                                                           "params": [float(x) for x in c.params]})
    seconds = {f"sfm_{k}": v for k, v in sfm.seconds.items()} | {"total": round(time.perf_counter() - t0, 2)}
    result = FrontendResult(views=out["views"], targets=out["targets"], probes=out["probes"], sfm=sfm,
                            calibration={}, colmap_cameras=colmap_cameras, alignment=diag, bundle=None,
                            target_pnp={}, checks=checks, seconds=seconds)
    atomic_write_text(work / "report.json", json.dumps(
        {"grade": result.grade, "checks": [c.model_dump() for c in checks], "sfm": sfm.model_dump(),
         "alignment": diag, "colmap_cameras": colmap_cameras, "seconds": seconds,
         "options": options.model_dump(mode="json")}, indent=2))
    return result
