"""Synthetic photo-stage inputs for the geometry and texture stages: a capture folder with ``[views]`` and
``[board]``, and the ``ingest`` and ``sfm`` artifact folders in their contract format (objcam/stages/ingest.py,
objcam/stages/sfm.py), rendered from the ring of views of :mod:`objcam.synth.views`.

Used by the tests and the benchmark so that geometry/texture can be built and measured independently of the
front end. What is written (``root`` = the returned paths' parent)::

    capture/capture.toml            [views], [board], one photo target (never read here); scene.object if given
    capture/object.ply              the known shape (optional), in its own frame and units (see ``known_shape``)
    ingest/views.json, ingest/views/<stem>.exr|.png   linear radiance (exposure 1) and its 8-bit sRGB copy
    sfm/cameras/views/<stem>.json   the true cameras, optionally perturbed by SfM-sized errors
    sfm/points.npz, sfm/report.json sparse points on the printed ring of the board (SfM finds no points on a
                                    textureless object), with noise and a few outliers
    truth/                          object.npz (world metres), cameras/<stem>.json, albedo_support.exr + extent
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.camera import Camera
from objcam.synth.views import ViewRingParams, ring_cameras, view_names


class SyntheticInputs(BaseModel):
    """Where :func:`write_inputs` put things."""

    model_config = ConfigDict(frozen=True)
    capture: Path
    ingest: Path
    sfm: Path
    truth: Path


class InputNoise(BaseModel):
    """SfM-sized errors added to the true cameras and the sparse points."""

    model_config = ConfigDict(extra="forbid")
    centre_mm: float = Field(0.2, ge=0, description="camera centre error, mm (std per axis / sqrt(3))")
    rotation_deg: float = Field(0.02, ge=0, description="camera rotation error, degrees (std of the angle)")
    points_mm: float = Field(0.15, ge=0, description="sparse point error, mm (std per axis)")
    n_points: int = Field(3000, ge=0, description="sparse points on the board's printed ring")
    outlier_fraction: float = Field(0.03, ge=0, le=0.5, description="fraction of gross outliers (up to 5 cm)")
    seed: int = 0


def perturb_camera(cam: Camera, rng: np.random.Generator, centre_mm: float, rotation_deg: float) -> Camera:
    """``cam`` with its centre moved by ~``centre_mm`` and its rotation by ~``rotation_deg`` (random axes)."""
    from scipy.spatial.transform import Rotation

    m = cam.matrix.copy()
    rv = rng.normal(size=3)
    rv *= np.radians(rotation_deg) * abs(rng.normal()) / np.linalg.norm(rv)
    m[:3, :3] = Rotation.from_rotvec(rv).as_matrix() @ m[:3, :3]
    m[:3, 3] += rng.normal(size=3) * centre_mm * 1e-3 / np.sqrt(3)
    return cam.model_copy(update={"world_from_camera": m.tolist()})


def board_ring_points(params: ViewRingParams, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points uniformly on the printed ring of the board (outside its blank centre), z = 0."""
    spec = params.board
    w, h = spec.size
    cols, rows = spec.blank_squares()
    bx0, bx1 = cols.start * spec.square_length - w / 2, cols.stop * spec.square_length - w / 2
    by0, by1 = h / 2 - rows.stop * spec.square_length, h / 2 - rows.start * spec.square_length
    out = np.zeros((0, 3))
    while len(out) < n:
        p = rng.uniform([-w / 2, -h / 2], [w / 2, h / 2], size=(2 * n, 2))
        blank = (p[:, 0] > bx0) & (p[:, 0] < bx1) & (p[:, 1] > by0) & (p[:, 1] < by1)
        p = p[~blank]
        out = np.concatenate([out, np.c_[p, np.zeros(len(p))]])
    return out[:n]


def known_shape_transform(scale: float = 1000.0, yaw_deg: float = 40.0) -> np.ndarray:
    """A 4x4 taking world metres to the known shape's own frame: y up (a common CAD/printer export), yawed by
    ``yaw_deg``, offset, in millimetres (``scale``)."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("x", -90, degrees=True) * Rotation.from_euler("z", yaw_deg, degrees=True)
    t = np.eye(4)
    t[:3, :3] = scale * rot.as_matrix()
    t[:3, 3] = [12.0, -3.0, 25.0]  # in the model's units
    return t


def write_inputs(root: str | Path, params: ViewRingParams | None = None, noise: InputNoise | None = None,
                 known_shape: bool = True, linear_exposure: float = 1.0) -> SyntheticInputs:
    """Render the views of ``params`` (linear radiance) and write a capture plus ingest/sfm artifacts under
    ``root`` (layout in the module docstring). ``known_shape``: also write the object as ``object.ply`` in
    millimetres in another frame (:func:`known_shape_transform`) and name it in capture.toml."""
    import cv2

    from objcam.envmap import rotate_z
    from objcam.image_io import atomic_write_text, save_npz, write_exr
    from objcam.progress import bar
    from objcam.render import mitsuba_box_bitmap, render_image
    from objcam.scene import AlbedoValue, MeshData, SceneDescription, build_mitsuba_scene, make_plane
    from objcam.sfm.board import board_texture
    from objcam.synth.assets import load_envmap, object_mesh, write_ply
    from objcam.synth.noise import apply_noise, auto_exposure

    params = params or ViewRingParams()
    noise = noise or InputNoise()
    root = Path(root)
    cap, ing, sfm, truth = root / "capture", root / "ingest", root / "sfm", root / "truth"
    for d in (cap, ing / "views", sfm / "cameras" / "views", truth / "cameras"):
        d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(noise.seed)

    verts, faces = object_mesh(params.object, params.object_height)
    tex = board_texture(params.board, params.texture_px_per_m)
    MeshData(verts, faces).save(truth / "object.npz")
    write_exr(truth / "albedo_support.exr", np.repeat(tex.image[..., None], 3, axis=2))
    make_plane(params.plane_size, tex.extent).save(truth / "support.npz")
    rgb = (params.object_albedo,) * 3 if isinstance(params.object_albedo, (int, float)) else params.object_albedo
    desc = SceneDescription(object_mesh="object.npz", support_mesh="support.npz", support_is_plane=True,
                            albedo_object=AlbedoValue(rgb=tuple(float(x) for x in rgb)),
                            albedo_support=AlbedoValue(texture="albedo_support.exr"))
    env = rotate_z(load_envmap(params.envmap, params.envmap_height).astype(np.float64), params.rotation_deg)
    scene = build_mitsuba_scene(desc, truth, envmap=mitsuba_box_bitmap(env.astype(np.float32),
                                                                       params.envmap_upsample))

    records, ref = [], None
    for i, (name, cam) in enumerate(zip(view_names(params), bar(ring_cameras(params), desc="views", unit="view"))):
        img = render_image(scene, cam, params.spp, params.max_depth, seed=1000 + i)
        if params.shot_noise > 0:
            img, _ = apply_noise(img, auto_exposure(img, params.shot_noise), 0.0, None,
                                 np.random.default_rng([params.seed, 11, i]))
        img = np.maximum(img, 0.0) * linear_exposure
        write_exr(ing / "views" / f"{name}.exr", img)
        if ref is None:
            ref = float(np.percentile(img, 99.0))
        disp = np.clip(img / ref, 0, 1) ** (1 / 2.2)
        cv2.imwrite(str(ing / "views" / f"{name}.png"), (disp[..., ::-1] * 255 + 0.5).astype(np.uint8))
        cam.save(truth / "cameras" / f"{name}.json")
        perturb_camera(cam, rng, noise.centre_mm, noise.rotation_deg).save(sfm / "cameras" / "views" / f"{name}.json")
        records.append({"name": name, "source": f"views/{name}.png", "width": cam.width, "height": cam.height,
                        "scale": 1.0, "exposure": {"time_s": 1.0, "iso": 100, "f_number": 8.0},
                        "white_balance": [1.0, 1.0, 1.0]})
    atomic_write_text(ing / "views.json", json.dumps(records, indent=2))

    pts = board_ring_points(params, noise.n_points, rng)
    pts += rng.normal(size=pts.shape) * noise.points_mm * 1e-3
    n_out = int(round(noise.outlier_fraction * len(pts)))
    pts[:n_out] += rng.uniform(-0.05, 0.05, size=(n_out, 3))
    save_npz(sfm / "points.npz", xyz=pts, rgb=np.full((len(pts), 3), 200, np.uint8),
             error=np.full(len(pts), 0.5), track=np.full(len(pts), 4, np.int64))
    atomic_write_text(sfm / "report.json", json.dumps({"registered": len(records), "total": len(records),
                                                       "synthetic": True}))

    obj_line = ""
    if known_shape:
        t = known_shape_transform()
        v = np.c_[verts.astype(np.float64), np.ones(len(verts))] @ t.T
        write_ply(cap / "object.ply", v[:, :3].astype(np.float32), faces)
        save_npz(truth / "known_from_world.npz", matrix=t)
        obj_line = 'object = "object.ply"\n'
    b = params.board
    toml = (f"[scene]\n{obj_line}plane_size = {params.plane_size}\n\n[views]\nfolder = \"views\"\n\n"
            f"[board]\nsquares_x = {b.squares_x}\nsquares_y = {b.squares_y}\nsquare_length = {b.square_length}\n"
            f"marker_length = {b.marker_length}\ndictionary = \"{b.dictionary}\"\nblank_x = {b.blank_x}\n"
            f"blank_y = {b.blank_y}\nmargin = {b.margin}\n\n[[targets]]\nname = \"t0\"\nfolder = \"targets/t0\"\n")
    atomic_write_text(cap / "capture.toml", toml)
    atomic_write_text(truth / "truth.json", json.dumps({"params": params.model_dump(), "board_extent": tex.extent,
                                                        "object_albedo": list(rgb)}, indent=2))
    return SyntheticInputs(capture=cap, ingest=ing, sfm=sfm, truth=truth)


class AlbedoError(BaseModel):
    """Albedo errors of a texture stage's output against the synthetic truth (absolute, albedo units)."""

    model_config = ConfigDict(frozen=True)
    support_median: float  # median |error| over the confident support texels
    support_p90: float
    paper_median: float  # ... over plain-paper texels only (no ink edges)
    object_median: float  # median |error| over the confident object texels (truth: a constant albedo)
    object_bias: float  # median (estimate - truth) on the object


def albedo_error(texture_dir: str | Path, truth_dir: str | Path, min_confidence: float = 0.5) -> AlbedoError:
    """Compare ``texture_dir``'s albedo_support.exr / albedo_object.exr with ``truth_dir`` (written by
    :func:`write_inputs`): the support against the board texture at each texel centre (mean over the true texels
    the estimated texel covers), the object against its constant albedo; grey (channel mean) values."""
    import cv2

    from objcam.image_io import read_exr

    tex_dir, truth_dir = Path(texture_dir), Path(truth_dir)
    info = json.loads((tex_dir / "texture.json").read_text())
    truth = json.loads((truth_dir / "truth.json").read_text())
    est = read_exr(tex_dir / "albedo_support.exr")[..., :3].mean(axis=2)
    conf = read_exr(tex_dir / "confidence_support.exr")[..., 0]
    true_img = read_exr(truth_dir / "albedo_support.exr")[..., :3].mean(axis=2)
    n = est.shape[0]
    ext, true_ext = info["support_extent_m"], truth["board_extent"]
    # true texture resampled onto the estimate's grid (area average: INTER_AREA), then placed by extent
    s = (np.arange(n) + 0.5) / n * ext - ext / 2  # texel centres, metres (column -> +x, row 0 at +y)
    m = true_img.shape[0]
    scale = ext / n * m / true_ext  # true texels per estimated texel
    small = cv2.resize(true_img, (max(1, int(round(m / scale))),) * 2, interpolation=cv2.INTER_AREA)
    k = small.shape[0]
    cc = np.clip(np.floor((s + true_ext / 2) / true_ext * k).astype(int), 0, k - 1)
    rr = np.clip(np.floor((true_ext / 2 - s) / true_ext * k).astype(int), 0, k - 1)
    inside = (np.abs(s) < true_ext / 2)
    tru = small[np.ix_(rr, cc)]
    tru = np.where(inside[:, None] & inside[None, :], tru, 0.8)  # paper beyond the print
    ok = conf >= min_confidence
    err = np.abs(est - tru)[ok]
    paper = (tru >= 0.8 - 1e-3)[ok]
    oest = read_exr(tex_dir / "albedo_object.exr")[..., :3].mean(axis=2)
    oconf = read_exr(tex_dir / "confidence_object.exr")[..., 0]
    oa = float(np.mean(truth["object_albedo"]))
    osel = oconf >= min_confidence
    return AlbedoError(support_median=float(np.median(err)), support_p90=float(np.percentile(err, 90)),
                       paper_median=float(np.median(err[paper])) if paper.any() else float("nan"),
                       object_median=float(np.median(np.abs(oest[osel] - oa))) if osel.any() else float("nan"),
                       object_bias=float(np.median(oest[osel] - oa)) if osel.any() else float("nan"))
