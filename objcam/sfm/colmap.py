"""Structure from motion with pycolmap (CPU): SIFT extraction, exhaustive matching, incremental mapping.

Views (the photogrammetry ring) and target images go through SfM together so every target gets a pose in the same
frame. Images are grouped by folder (``images/<group>/<name>``); every group shares one COLMAP camera (one physical
camera and zoom setting), with known intrinsics optional.

Layout written by :func:`run_sfm` under ``work_dir``::

    database.db            COLMAP database (features, matches)
    sparse_sfm/0/          the model as COLMAP's mapper wrote it (arbitrary frame and scale), binary format
    (``objcam.sfm.align`` writes the metric, board-aligned model to ``sparse/0/``)

Conventions: COLMAP puts pixel centres at +0.5 (principal point cx = W / 2 for a centred one); objcam / OpenCV at
integers, so objcam cx = COLMAP cx - 0.5 (:func:`camera_to_colmap_params`, ``objcam.sfm.align.objcam_camera``).
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path
from typing import Literal, Mapping, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.camera import Camera
from objcam.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
HDR_SUFFIXES = (".exr", ".hdr")
MIN_VIEWS = 3


class SfmOptions(BaseModel):
    """pycolmap settings that matter here."""

    model_config = ConfigDict(extra="forbid")
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = Field(
        "PINHOLE", description="COLMAP camera model for groups without known intrinsics")
    refine_intrinsics: bool = Field(True, description="let bundle adjustment refine the focal length(s) "
                                    "(known intrinsics are always held fixed)")
    max_image_size: int = Field(1600, ge=64, description="SIFT on images downscaled to this size (longest side)")
    max_num_features: int = Field(8192, ge=256, description="SIFT features per image")
    num_threads: int = Field(2, ge=1, description="CPU threads for feature extraction and matching (the mapper "
                             "runs on one: repeatable models)")
    min_registered_fraction: float = Field(0.5, ge=0, le=1, description="fewer registered images is an error")
    seed: int = Field(0, ge=0, description="random seed of the mapper (repeatable runs)")
    init_min_num_inliers: int = Field(50, ge=15, description="inlier matches an initial pair needs (COLMAP: 100)")
    init_min_tri_angle: float = Field(8.0, gt=0, description="triangulation angle of the initial pair, degrees "
                                      "(COLMAP: 16)")
    quiet_log: bool = Field(True, description="hide COLMAP's INFO log lines (its warnings print after a "
                            "successful run; a failed one is the InputError's one line)")


class SfmResult(BaseModel):
    """What :func:`run_sfm` did and how well."""

    model_config = ConfigDict(extra="forbid")
    model_dir: str  # sparse_sfm/0
    image_dir: str
    images: list[str]  # every image given, relative to image_dir
    registered: list[str]
    unregistered: list[str]
    seeded: bool | Literal["held"]  # started from given poses (seed_poses); "held": those poses held fixed, after
    # the mapper's adjustment of them collapsed the model (:func:`collapsed`)
    num_points3D: int
    mean_reprojection_error_px: float
    mean_track_length: float
    seconds: dict[str, float]

    @property
    def registered_fraction(self) -> float:
        return len(self.registered) / max(1, len(self.images))

    def load(self):
        import pycolmap

        return pycolmap.Reconstruction(self.model_dir)


def camera_to_colmap_params(camera: Camera, model: str = "PINHOLE") -> list[float]:
    """COLMAP parameters of an objcam camera's intrinsics (principal point + 0.5)."""
    cx, cy = camera.cx + 0.5, camera.cy + 0.5
    if model == "PINHOLE":
        return [camera.fx, camera.fy, cx, cy]
    if model == "SIMPLE_PINHOLE":
        return [0.5 * (camera.fx + camera.fy), cx, cy]
    if model == "SIMPLE_RADIAL":
        return [0.5 * (camera.fx + camera.fy), cx, cy, 0.0]
    if model == "RADIAL":
        return [0.5 * (camera.fx + camera.fy), cx, cy, 0.0, 0.0]
    if model == "OPENCV":
        return [camera.fx, camera.fy, cx, cy, 0.0, 0.0, 0.0, 0.0]
    raise ValueError(f"unsupported camera model {model!r}")


def _hdr_to_png(src: Path, dst: Path) -> None:
    import cv2

    from objcam.image_io import atomic_write_bytes, read_exr, tonemap

    img = read_exr(src)[..., :3]
    disp, _ = tonemap(img)
    q = (np.clip(disp, 0, 1) * 255.0 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(q[..., ::-1]))
    if not ok:
        raise OSError(f"cannot encode {dst}")
    atomic_write_bytes(dst, buf.tobytes())


def prepare_images(image_dir: str | Path, groups: Mapping[str, Sequence[str | Path]],
                   copy: bool = False) -> dict[str, list[str]]:
    """Gather images for SfM under ``image_dir/<group>/``: 8/16-bit PNG, JPEG and TIFF files are linked (or, with
    ``copy`` or where links fail, copied: a folder that is moved afterwards keeps working), linear HDR (EXR)
    targets are tonemapped to 8-bit PNG. Returns {group: [name relative to image_dir]}.

    groups: {group name (a folder name, e.g. "views", "targets"): image paths}; file stems must be unique per group.
    """
    root = Path(image_dir)
    out: dict[str, list[str]] = {}
    for group, paths in groups.items():
        d = root / group
        d.mkdir(parents=True, exist_ok=True)
        names = []
        seen: set[str] = set()
        for p in map(Path, paths):
            if not p.is_file():
                raise InputError("image not found", p, "check the path")
            suf = p.suffix.lower()
            if p.stem in seen:
                raise InputError(f"two images named {p.stem!r} in group {group!r}", p, "give images unique names")
            seen.add(p.stem)
            if suf in HDR_SUFFIXES:
                dst = d / f"{p.stem}.png"
                _hdr_to_png(p, dst)
            elif suf in IMAGE_SUFFIXES:
                dst = d / p.name
                if dst.exists() or dst.is_symlink():
                    dst.unlink()
                try:
                    if copy:
                        raise OSError("copy requested")
                    dst.symlink_to(p.resolve())
                except OSError:
                    shutil.copy2(p, dst)
            else:
                raise InputError(f"unsupported image type {p.suffix!r}", p, "give PNG, JPEG, TIFF or EXR images")
            names.append(f"{group}/{dst.name}")
        out[group] = names
    return out


def run_sfm(work_dir: str | Path, image_dir: str | Path, groups: Mapping[str, Sequence[str]],
            intrinsics: Mapping[str, Camera] | None = None, options: SfmOptions | None = None,
            error_path: str | Path | None = None,
            initial_intrinsics: Mapping[str, tuple[Camera, list[float]]] | None = None,
            seed_poses: Mapping[str, Camera] | None = None,
            camera_of: Mapping[str, str] | None = None) -> SfmResult:
    """SfM over the images ``groups`` ({group: [names relative to image_dir]}, e.g. from :func:`prepare_images`).

    intrinsics: optional {group: Camera} whose fx, fy, cx, cy are known (held fixed, PINHOLE).
    initial_intrinsics: optional {group: (Camera, OpenCV distortion [k1, ...])}: a starting point (e.g. from the
    board, ``objcam.sfm.align.calibrate_intrinsics``) that COLMAP treats as a prior focal length and refines
    (``options.refine_intrinsics``); k1 is used by the radial models. Other groups get ``options.camera_model``
    with COLMAP's default initial focal length (1.2 x the longer side).
    seed_poses: optional {image name: Camera (world frame, e.g. board PnP)}: with two or more, the model starts
    from these poses (``pycolmap.triangulate_points``) and the incremental mapper registers the other images and
    bundle-adjusts everything (robust where SIFT alone finds too few matches for an initial pair: small, noisy
    or nearly planar scenes). The model is then already in the world frame, up to the mapper's adjustments.
    camera_of: optional {group: camera group}: groups mapped to the same camera group share one COLMAP camera
    (one camera body and zoom setting; their images must have one size); ``intrinsics`` and
    ``initial_intrinsics`` are looked up by camera group. Default: every group its own camera.
    Writes ``work_dir/database.db`` and ``work_dir/sparse_sfm/0`` (binary). Raises InputError when there are too
    few images or too few register (naming the images that did not, and ``error_path``, default ``image_dir``).
    """
    import pycolmap

    options = options or SfmOptions()
    intrinsics = dict(intrinsics or {})
    work = Path(work_dir)
    image_dir = Path(image_dir)
    where = Path(error_path) if error_path is not None else image_dir
    all_names = [n for names in groups.values() for n in names]
    if len(all_names) < MIN_VIEWS:
        raise InputError(f"only {len(all_names)} image(s) for structure from motion", where,
                         f"take at least {MIN_VIEWS} (better 20 or more) overlapping views around the object")
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    db.unlink(missing_ok=True)
    sparse = work / "sparse_sfm"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    pycolmap.set_random_seed(options.seed)
    if options.quiet_log:  # COLMAP's INFO lines (thousands) would drown the stage's own output
        pycolmap.logging.minloglevel = 1
    seconds: dict[str, float] = {}

    def colmap() -> tuple[dict, bool]:
        seeded = False
        t = time.perf_counter()
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = options.num_threads
        ext.max_image_size = options.max_image_size
        ext.sift.max_num_features = options.max_num_features
        pycolmap.Database.open(db).close()  # an empty database (import_images wants one)
        # one group at a time, in ``groups``' order (the ring of views first): COLMAP numbers the images in the
        # order they are imported (by name within one import), and its mapper fixes the bundle adjustment's gauge
        # on the first two. Imported as one camera group, "probes/" and "targets/" sort before "views/": two
        # chrome-ball shots from one tripod, 2 mm apart, were images 1 and 2 and collapsed a seeded model
        # (bench/results.md, sessions 52-53). Groups of one camera group share its COLMAP camera.
        camera_ids: dict[str, int] = {}
        for source, names in groups.items():
            if not names:
                continue
            group = (camera_of or {}).get(source, source)
            known = intrinsics.get(group)
            guess = (initial_intrinsics or {}).get(group)
            reader = pycolmap.ImageReaderOptions()
            if known is not None:
                reader.camera_model = "PINHOLE"
                reader.camera_params = ",".join(repr(float(x)) for x in camera_to_colmap_params(known, "PINHOLE"))
            elif guess is not None:
                reader.camera_model = options.camera_model
                params = camera_to_colmap_params(guess[0], options.camera_model)
                if options.camera_model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV") and guess[1]:
                    params[{"SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4}[options.camera_model]] = float(guess[1][0])
                reader.camera_params = ",".join(repr(float(x)) for x in params)
            else:
                reader.camera_model = options.camera_model
            if group in camera_ids:
                reader.existing_camera_id = camera_ids[group]
            # the images first, one by one: the extractor's threads would add them in the order they finish, and
            # COLMAP's image ids (which order the mapper's choices) would differ from run to run
            pycolmap.import_images(db, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=list(names),
                                   options=reader)
            if group not in camera_ids:
                with pycolmap.Database.open(db) as opened:
                    camera_ids[group] = opened.read_image_with_name(names[0]).camera_id
            pycolmap.extract_features(db, image_dir, image_names=list(names), camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        seconds["extract"] = time.perf_counter() - t

        t = time.perf_counter()
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = options.num_threads
        verify = pycolmap.TwoViewGeometryOptions()
        verify.ransac.random_seed = options.seed
        pycolmap.match_exhaustive(db, matching_options=match, verification_options=verify, device=pycolmap.Device.cpu)
        seconds["match"] = time.perf_counter() - t

        t = time.perf_counter()
        mo = pycolmap.IncrementalPipelineOptions()
        # one thread: pycolmap 4.2's mapper with two is not repeatable even with random_seed set (one database,
        # six runs: five or six different models, 272-292 points; one thread: the same model every run). Mapping
        # is the cheap step here (~0.1 s of the stage's ~3 s)
        mo.num_threads = 1
        mo.random_seed = options.seed
        mo.min_model_size = min(mo.min_model_size, max(2, len(all_names) // 2))
        # small, nearly planar tabletop scenes: fewer matches than COLMAP's defaults expect
        mo.mapper.init_min_num_inliers = options.init_min_num_inliers
        mo.mapper.abs_pose_min_num_inliers = min(mo.mapper.abs_pose_min_num_inliers, options.init_min_num_inliers)
        mo.mapper.init_min_tri_angle = options.init_min_tri_angle
        fixed_ids = _fixed_camera_ids(db, camera_groups(groups, camera_of), intrinsics)
        if fixed_ids:
            mo.constant_cameras = set(fixed_ids)
        if not options.refine_intrinsics:
            mo.ba_refine_focal_length = False
            mo.ba_refine_extra_params = False
        mo.ba_refine_principal_point = False
        if seed_poses and len([n for n in seed_poses if n in all_names]) >= 2:
            seed_dir = work / "seed"
            if seed_dir.exists():
                shutil.rmtree(seed_dir)
            seed = _seed_model(db, seed_poses)
            tri = pycolmap.triangulate_points(seed, db, image_dir, _mk(seed_dir), options=mo)
            tri.write(str(seed_dir))
            models = pycolmap.incremental_mapping(db, image_dir, sparse, options=mo, input_path=seed_dir)
            seeded = True
            if collapsed(models, tri.num_points3D()):
                # the mapper's global bundle adjustment can collapse a seeded model (pycolmap 4.2: "Failed to fix
                # Gauge", final cost 0, every point filtered; seen where COLMAP's first two images were two
                # chrome-ball shots from one tripod, 2 mm apart, which the import order above now prevents; kept
                # as a guard): map again with the seeds' board poses held
                seeded = "held"
                shutil.rmtree(sparse)
                sparse.mkdir(parents=True)
                mo.fix_existing_frames = True
                models = pycolmap.incremental_mapping(db, image_dir, sparse, options=mo, input_path=seed_dir)
            shutil.rmtree(seed_dir, ignore_errors=True)
        else:
            models = pycolmap.incremental_mapping(db, image_dir, sparse, options=mo)
        seconds["map"] = time.perf_counter() - t
        return models, seeded

    # COLMAP logs warnings and errors (glog) straight to file descriptor 2; a failed run is reported in one line
    # below, so its log lines are shown only when SfM succeeds
    from objcam.capture.raw import capture_c_stderr

    with capture_c_stderr() as log:
        models, seeded = colmap()
    log_text = "".join(log)

    def echo_log() -> None:
        if log_text:
            sys.stderr.write(log_text)

    if not models:
        raise InputError(f"structure from motion registered none of the {len(all_names)} images", where,
                         "take more views with more overlap (neighbouring views 10-20 degrees apart), sharp and "
                         "well exposed, with the textured board in view")
    best_idx = max(models, key=lambda k: models[k].num_reg_images())
    rec = models[best_idx]
    shutil.rmtree(sparse)  # whatever the mapper wrote (layouts differ with and without input_path)
    model_dir = _mk(sparse / "0")
    rec.write(str(model_dir))
    reg = {img.name for img in rec.images.values() if img.has_pose}
    registered = [n for n in all_names if n in reg]
    unregistered = [n for n in all_names if n not in reg]
    result = SfmResult(model_dir=str(model_dir), image_dir=str(image_dir), images=all_names, registered=registered,
                       unregistered=unregistered, seeded=seeded, num_points3D=rec.num_points3D(),
                       mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
                       mean_track_length=float(rec.compute_mean_track_length()),
                       seconds={k: round(v, 2) for k, v in seconds.items()})
    if result.registered_fraction < options.min_registered_fraction or len(registered) < MIN_VIEWS:
        shown = ", ".join(unregistered[:6]) + (" ..." if len(unregistered) > 6 else "")
        raise InputError(f"structure from motion registered only {len(registered)}/{len(all_names)} images "
                         f"(not: {shown})", where,
                         "add views with more overlap (neighbouring views 10-20 degrees apart), keep the board "
                         "and the object in every view, avoid blur")
    echo_log()
    return result


def collapsed(models: Mapping, seed_points: int) -> bool:
    """Whether the mapper's models, started from a seed model of ``seed_points`` triangulated points, kept fewer
    than a tenth of them in the model with the most registered images (a bundle adjustment that collapsed the
    model drops every observation; a healthy seeded run keeps about as many as it started with, and more)."""
    if not models or seed_points <= 0:
        return False
    best = max(models.values(), key=lambda m: m.num_reg_images())
    return best.num_points3D() < 0.1 * seed_points


def camera_groups(groups: Mapping[str, Sequence[str]], camera_of: Mapping[str, str] | None) -> dict[str, list[str]]:
    """{camera group: image names} from {group: image names} and {group: camera group} (default: itself)."""
    out: dict[str, list[str]] = {}
    for group, names in groups.items():
        out.setdefault((camera_of or {}).get(group, group), []).extend(names)
    return out


def _seed_model(db: Path, poses: Mapping[str, Camera]):
    """A pycolmap Reconstruction holding the database's cameras and the images of ``poses`` at those poses
    (keypoints from the database, no points yet)."""
    import pycolmap

    database = pycolmap.Database.open(db)
    try:
        rec = pycolmap.Reconstruction()
        for cam in database.read_all_cameras():
            rec.add_camera_with_trivial_rig(cam)
        for img in database.read_all_images():
            if img.name not in poses:
                continue
            kp = np.asarray(database.read_keypoints(img.image_id), dtype=np.float64)[:, :2]
            im = pycolmap.Image(name=img.name, keypoints=kp, camera_id=img.camera_id, image_id=img.image_id)
            cfw = np.linalg.inv(poses[img.name].matrix)[:3]
            rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(cfw))
    finally:
        database.close()
    return rec


def _mk(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


def _fixed_camera_ids(db: Path, groups: Mapping[str, Sequence[str]], intrinsics: Mapping[str, Camera]) -> list[int]:
    """COLMAP camera ids of the groups with known intrinsics."""
    if not intrinsics:
        return []
    import pycolmap

    want = {n for g, names in groups.items() if g in intrinsics for n in names}
    ids = set()
    database = pycolmap.Database.open(db)
    try:
        for img in database.read_all_images():
            if img.name in want:
                ids.add(int(img.camera_id))
    finally:
        database.close()
    return sorted(ids)
