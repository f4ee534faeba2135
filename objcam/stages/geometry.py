"""Stage ``geometry``: object and support meshes in world metres from the photos (issue 4).

Applies when the capture has ``[views]`` (so sfm has posed them). Known shape (``scene.object``): registered to
the reconstruction; otherwise reconstructed from silhouettes. Writes:
    object.npz, support.npz        MeshData (objcam.scene), world metres, object resting on z = 0
    hull.npz                       the carved visual hull (MeshData), what a known shape is registered to
    masks/<stem>.png               object silhouette per view (255 object, 128 no evidence, 0 background), as carved
    geometry.json                  plane fit residual (mm), registration residual (mm) or reconstruction stats

Steps: robust plane fit to the sparse points and the board's triangulated corners (checks the world frame and the
support's flatness); silhouettes by plane-induced parallax (objcam.geometry.silhouette); the visual hull
(objcam.geometry.hull: outlines moved onto the image's edges, a robust hull, background pixels the object explains
marked unknown, the final coarse-to-fine carving over the volume above the board's blank centre, surface nets +
pymeshlab cleaning); for a known shape, unit detection, registration to the hull (objcam.geometry.register) and
refinement against the silhouettes (objcam.geometry.silfit).

Bad input stops the stage with one line before anything is written (a mesh that is empty, non-manifold, of no
plausible unit or far from any plausible registration; too few support points or registered views): every file
is written at the end, and the engine renames the folder into place only when the stage returns.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.errors import InputError
from objcam.geometry.ambiguity import AmbiguityParams
from objcam.geometry.carve import CarveParams
from objcam.geometry.outline import OutlineParams
from objcam.geometry.register import RegisterParams
from objcam.geometry.silhouette import SilhouetteParams
from objcam.geometry.surface import MeshingParams
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.capture import CaptureManifest, try_load

NAME = "geometry"
DEPS: tuple[str, ...] = ("ingest", "sfm")
VERSION = "2"
APPLIES_WHEN = "the capture has [views]"  # via DEPS: applies wherever sfm does



def input_files(capture: Path) -> list[Path]:
    """capture.toml and the known shape, if any (their contents key the cache)."""
    files = [Path(capture) / "capture.toml"]
    m = try_load(capture)
    if m is not None and m.scene.object is not None:
        files.append(Path(capture) / m.scene.object)
    return files


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    min_views: int = Field(6, ge=3, description="fewest registered views to carve from")
    plane_threshold_mm: float = Field(1.0, gt=0, description="RANSAC inlier distance, mm")
    flat_rms_mm: float = Field(0.5, gt=0, description="a support whose inlier RMS exceeds this is reported as "
                               "not flat")
    min_support_points: int = Field(20, ge=3, description="fewest points near z = 0 for the plane fit")
    board_corners: bool = Field(True, description="add the board's corners, detected in the views' sRGB copies "
                                "and triangulated, to the plane fit")
    volume: tuple[float, float, float] | None = Field(
        None, description="carving volume (x, y, z extent, metres, centred on the origin in x and y, from z = 0); "
        "default: the board's blank centre, as tall as it is wide")
    voxel_size: float | None = Field(None, gt=0, description="finest voxel, metres; default: about one pixel's "
                                     "footprint at the object")
    max_object_faces: int = Field(12000, ge=100, description="the object mesh is decimated to this many faces")
    silhouette: SilhouetteParams = SilhouetteParams()
    outline: OutlineParams = OutlineParams()
    ambiguity: AmbiguityParams = AmbiguityParams()
    carve: CarveParams = CarveParams()
    meshing: MeshingParams = MeshingParams()
    registration: RegisterParams = RegisterParams()


def _volume(manifest: CaptureManifest, params: Params) -> tuple[np.ndarray, np.ndarray]:
    if params.volume is not None:
        w, d, h = params.volume
    elif manifest.board is not None:
        b = manifest.board
        cols, rows = b.blank_squares()
        w, d = len(cols) * b.square_length, len(rows) * b.square_length
        h = max(w, d)
    else:
        s = manifest.scale.object_height if manifest.scale is not None else 0.3
        w = d = 2.0 * s
        h = 1.5 * s
    return np.array([-w / 2, -d / 2, 0.0]), np.array([w / 2, d / 2, h])


def _auto_voxel(cams: list, lo: np.ndarray, hi: np.ndarray) -> float:
    """About one pixel's footprint at the volume's centre (median over the views), but no finer than 1/400 of
    the volume: the field is interpolated to a fraction of a voxel, so finer voxels buy little."""
    c = (lo + hi) / 2
    c[2] = (hi[2] - lo[2]) / 4
    foot = np.median([np.linalg.norm(cam.centre - c) / cam.fx for cam in cams])
    return float(max(foot, float(np.max(hi - lo)) / 400))


def _plane(inputs: StageInputs, manifest: CaptureManifest, views, params: Params):
    from objcam.geometry.plane import board_corner_points, fit_plane
    from objcam.geometry.views import load_points

    pts = load_points(inputs.upstream["sfm"])
    near = pts[np.abs(pts[:, 2]) < 0.02] if len(pts) else pts  # points far off z = 0 are not support candidates
    n_corners = 0
    if params.board_corners and manifest.board is not None:
        pngs = [inputs.upstream["ingest"] / "views" / f"{v.name}.png" for v in views]
        ok = [p.is_file() for p in pngs]
        corners = board_corner_points([p for p, o in zip(pngs, ok) if o], [v.camera for v, o in zip(views, ok) if o],
                                      manifest.board)
        n_corners = len(corners)
        near = np.concatenate([near, corners]) if len(near) else corners
    if len(near) < params.min_support_points:
        raise InputError(f"only {len(near)} points lie near the support plane z = 0 (need "
                         f"{params.min_support_points})", inputs.upstream["sfm"] / "points.npz",
                         "photograph the board and paper around the object (textured support), and rerun sfm")
    return fit_plane(near, threshold=params.plane_threshold_mm * 1e-3), n_corners


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    import cv2

    from objcam.geometry.hull import build_hull
    from objcam.geometry.meshcheck import check_known_mesh
    from objcam.geometry.register import apply, register, with_silhouette_fit
    from objcam.geometry.silfit import fit as silhouette_fit
    from objcam.geometry.silhouette import silhouettes, volume_roi
    from objcam.geometry.surface import decimate
    from objcam.geometry.views import load_views
    from objcam.image_io import atomic_write_text
    from objcam.scene import load_mesh, make_plane

    manifest = CaptureManifest.load(inputs.capture)
    out = inputs.out
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    views = load_views(inputs.upstream["ingest"], inputs.upstream["sfm"], params.min_views)
    known = None
    if manifest.scene.object is not None:  # load first: a bad mesh fails before minutes of work
        known = load_mesh(inputs.capture / manifest.scene.object)
        check_known_mesh(known, inputs.capture / manifest.scene.object)
    times["load"] = time.perf_counter() - t0

    t = time.perf_counter()
    plane, n_corners = _plane(inputs, manifest, views, params)
    times["plane"] = time.perf_counter() - t

    t = time.perf_counter()
    cams = [v.camera for v in views]
    lo, hi = _volume(manifest, params)
    # only the pixels where the carving volume projects are ever sampled: decide those only (~5x faster)
    rois = [volume_roi(c, lo, hi) for c in cams]
    masks = silhouettes(views, params.silhouette, progress=not inputs.quiet, rois=rois)
    times["silhouettes"] = time.perf_counter() - t

    t = time.perf_counter()
    voxel = params.voxel_size or _auto_voxel(cams, lo, hi)
    images = [v.image for v in views]
    built = build_hull(images, masks, cams, lo, hi, params.carve.model_copy(update={"voxel_size": voxel}),
                       params.outline, params.ambiguity, params.meshing)
    hull, field = built.mesh, built.field
    if len(hull.faces) == 0:
        raise InputError("carving left nothing: no view shows an object standing on the board",
                         inputs.upstream["ingest"] / "views", "photograph the object standing on the board's centre")
    times["carve_and_mesh"] = time.perf_counter() - t
    hlo, hhi = hull.bbox
    # a hull that reaches the volume's sides or top was cut by it: the object (or a mask error) is larger
    touches = bool(np.any(hlo[:2] <= lo[:2] + 2 * voxel) or np.any(hhi >= hi - 2 * voxel))

    metrics: dict = {
        "views": len(views), "board_corners": n_corners,
        "plane": plane.model_dump(), "support_flat": plane.rms_mm <= params.flat_rms_mm,
        # how far the fitted plane strays from the world's z = 0 anywhere over the carving volume's footprint
        "plane_deviation_mm": plane.deviation_mm(float(np.linalg.norm(hi[:2]))),
        "voxel_mm": voxel * 1e3, "carve_samples": field.evaluated,
        "hull_faces": int(len(hull.faces)), "hull_height_mm": float(hhi[2] - hlo[2]) * 1e3,
        "hull_volume_cm3": field.occupied_volume * 1e6, "hull_touches_volume": touches, **built.stats,
    }
    t = time.perf_counter()
    if known is not None:
        path = inputs.capture / manifest.scene.object
        reg = register(known, hull, params.registration, path)
        if params.registration.silhouette_fit.enabled:
            sf = silhouette_fit(apply(known, reg), masks, cams, params.registration.silhouette_fit, images)
            reg = with_silhouette_fit(reg, sf, params.registration.min_silhouette_agreement, path)
        obj = apply(known, reg)
        metrics["registration"] = reg.model_dump()
        metrics["object_source"] = "known shape, registered"
    else:
        obj = hull
        metrics["object_source"] = "reconstructed (visual hull)"
    obj = decimate(obj, params.max_object_faces)
    obj.vertices[:, 2] -= obj.vertices[:, 2].min()  # decimation moves vertices: rest exactly on z = 0
    times["object"] = time.perf_counter() - t
    # every check has passed: write
    (out / "masks").mkdir(parents=True, exist_ok=True)
    for v, (m, k, _) in zip(views, built.masks):  # ambiguous pixels: no evidence
        cv2.imwrite(str(out / "masks" / f"{v.name}.png"), np.where(k, np.where(m, 255, 0), 128).astype(np.uint8))
    hull.save(out / "hull.npz")
    obj.save(out / "object.npz")
    # the support: the plane z = 0 (flatness is checked above; a non-flat support is reported, not modelled)
    make_plane(manifest.scene.plane_size).save(out / "support.npz")
    olo, ohi = obj.bbox
    metrics.update(object_faces=int(len(obj.faces)), object_height_mm=float(ohi[2] - olo[2]) * 1e3,
                   seconds=times)
    atomic_write_text(out / "geometry.json", json.dumps(metrics, indent=2))
    if known is not None:
        r = metrics["registration"]
        sil = r.get("silhouette")
        reg_txt = (f"registered {r['unit']} model, residual {r['rms_mm']:.2f} mm to the hull"
                   + (f", {sil['rms_px']:.2f} px to the silhouettes" if sil else ""))
    else:
        reg_txt = "reconstructed from silhouettes"
    flat = "" if metrics["support_flat"] else " (support NOT flat)"
    summary = (f"{len(views)} views; plane RMS {plane.rms_mm:.2f} mm, tilt {plane.tilt_deg:.3f} deg{flat}; "
               f"object {reg_txt}, {metrics['object_height_mm']:.1f} mm tall, {len(obj.faces):,} faces")
    return StageOutputs(metrics=metrics, summary=summary)
