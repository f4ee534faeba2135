"""objcam.geometry and the geometry stage, against synthetic ground truth.

One small photographed capture (12 views at 256 x 192, 16 spp, direct light, cameras perturbed by SfM-sized
errors; the known bunny given in millimetres, y up, yawed) is rendered once per session in the ingest/sfm
contract format (objcam.synth.geometry_inputs) and shared with tests/test_texture.py.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from objcam.errors import InputError
from objcam.pipeline.stage import StageInputs
from objcam.scene import MeshData, load_mesh
from objcam.synth.geometry_inputs import write_inputs
from objcam.synth.views import ViewRingParams

SMALL = dict(n_views=12, width=256, height=192, spp=16, max_depth=2, distance=0.3, fov_deg=50.0,
             elevations_deg=[30.0, 50.0])
HEIGHT = 0.08  # ViewRingParams' default object height, metres


@pytest.fixture(scope="session")
def photo_capture(tmp_path_factory):
    return write_inputs(tmp_path_factory.mktemp("session_geometry_capture"), ViewRingParams(**SMALL))


@pytest.fixture(scope="session")
def geometry_run(photo_capture, tmp_path_factory):
    """(out folder, metrics) of the geometry stage on the shared capture."""
    from objcam.stages import geometry

    out = tmp_path_factory.mktemp("session_geometry_out")
    res = geometry.run(StageInputs(capture=photo_capture.capture, out=out, quiet=True,
                                   upstream={"ingest": photo_capture.ingest, "sfm": photo_capture.sfm}),
                       geometry.Params())
    return out, res.metrics


# ------------------------------------------------------------------------------------------------ the stage


def test_plane_matches_world_frame(geometry_run):
    _, m = geometry_run
    # sparse points carry 0.15 mm noise per axis (+3% outliers): the inlier RMS is that noise, the fitted plane
    # itself lies within 0.25 mm of z = 0 everywhere over the volume (measured 0.003 mm)
    assert m["plane_deviation_mm"] < 0.25
    assert 0.1 < m["plane"]["rms_mm"] < 0.25
    assert m["support_flat"] and m["board_corners"] >= 12
    # broken frames miss these bounds: test_a_broken_world_frame_fails_the_plane_bounds


def _plane_check(photo_capture, sfm, tmp_path, **params) -> dict:
    """The stage's plane checks (its plane fit to the sparse points and triangulated board corners, and the
    deviation over the carving volume) on the sfm folder ``sfm``, without the rest of the stage."""
    from objcam.geometry.views import load_views
    from objcam.schemas.capture import CaptureManifest
    from objcam.stages import geometry

    prm = geometry.Params(**params)
    manifest = CaptureManifest.load(photo_capture.capture)
    inputs = StageInputs(capture=photo_capture.capture, out=tmp_path, quiet=True,
                         upstream={"ingest": photo_capture.ingest, "sfm": sfm})
    plane, corners = geometry._plane(inputs, manifest, load_views(photo_capture.ingest, sfm), prm)
    _, hi = geometry._volume(manifest, prm)
    return {"plane_deviation_mm": plane.deviation_mm(float(np.linalg.norm(hi[:2]))), "plane": plane.model_dump(),
            "support_flat": plane.rms_mm <= prm.flat_rms_mm, "board_corners": corners}


def _plane_ok(m: dict) -> bool:
    """test_plane_matches_world_frame's bounds."""
    return bool(m["plane_deviation_mm"] < 0.25 and 0.1 < m["plane"]["rms_mm"] < 0.25 and m["support_flat"]
                and m["board_corners"] >= 12)


# broken world frames and plane fits: what a board alignment off by a fifth of a degree, a frame half a
# millimetre high (a board thickness), or an inlier threshold that takes the object's lowest points would give
BROKEN_PLANE = {"frame tilted 0.2 degrees": ("tilt", 0.2), "frame raised 0.5 mm": ("raise", 0.5e-3),
                "inlier threshold 20 mm": ("threshold", 20.0)}


@pytest.mark.parametrize("broken", list(BROKEN_PLANE))
def test_a_broken_world_frame_fails_the_plane_bounds(geometry_run, photo_capture, tmp_path, broken):
    """A test of the test (tests/broken.py): the plane checks above, rerun on the same views with the world frame
    moved (every SfM camera and point) or the plane fit loosened, miss the bounds (measured deviation / RMS:
    tilted 0.46 / 0.15 mm, raised 0.50 / 0.15 mm, loose threshold 0.04 / 1.08 mm; bounds 0.25 and 0.1 .. 0.25 mm).
    The stage's own metrics (test_plane_matches_world_frame) pass the same helper's bounds, so the helper is the
    stage's check."""
    from scipy.spatial.transform import Rotation

    from objcam.camera import Camera

    _, m = geometry_run
    kind, amount = BROKEN_PLANE[broken]
    assert _plane_ok(m)
    sfm, params = photo_capture.sfm, {}
    if kind == "threshold":
        params = {"plane_threshold_mm": amount}
    else:
        T = np.eye(4)
        if kind == "tilt":
            T[:3, :3] = Rotation.from_euler("x", amount, degrees=True).as_matrix()
        else:
            T[2, 3] = amount
        sfm = tmp_path / "sfm"
        shutil.copytree(photo_capture.sfm, sfm)
        for p in (sfm / "cameras" / "views").glob("*.json"):
            cam = Camera.load(p)
            cam.model_copy(update={"world_from_camera": (T @ np.asarray(cam.world_from_camera)).tolist()}).save(p)
        with np.load(sfm / "points.npz") as z:
            arrays = {k: z[k] for k in z.files}
        arrays["xyz"] = arrays["xyz"] @ T[:3, :3].T + T[:3, 3]
        np.savez(sfm / "points.npz", **arrays)
    bad = _plane_check(photo_capture, sfm, tmp_path / "out", **params)
    print(broken, bad["plane_deviation_mm"], bad["plane"]["rms_mm"], bad["board_corners"])
    assert not _plane_ok(bad), bad


def _registration_error(world_from_model: np.ndarray, photo_capture) -> np.ndarray:
    """(V,) metres: the known model's vertices placed by ``world_from_model`` (then set on z = 0, as the stage
    does) against the true object's."""
    known = load_mesh(photo_capture.capture / "object.ply")
    w = np.asarray(world_from_model)
    v = known.vertices.astype(np.float64) @ w[:3, :3].T + w[:3, 3]
    v[:, 2] -= v[:, 2].min()
    truth = MeshData.load_npz(photo_capture.truth / "object.npz").vertices.astype(np.float64)
    return np.linalg.norm(v - truth, axis=1)


def _height_mm(world_from_model: np.ndarray, photo_capture) -> float:
    """The known model's height (mm) once placed by ``world_from_model``: its vertices' extent along z."""
    v = load_mesh(photo_capture.capture / "object.ply").vertices.astype(np.float64)
    z = v @ np.asarray(world_from_model)[2, :3]
    return float(z.max() - z.min()) * 1e3


def _registration_ok(err: np.ndarray) -> bool:
    return bool(err.mean() < 0.4e-3 and err.max() < 0.8e-3)


def test_known_shape_registration(geometry_run, photo_capture):
    out, m = geometry_run
    reg = m["registration"]
    assert reg["unit"] == "mm" and reg["up_axis"] == "+y"
    err = _registration_error(reg["world_from_model"], photo_capture)
    # vertex-to-vertex error of the registered model: 0.7 mm mean after ICP to the hull, 0.16 mm mean (0.28 mm
    # max) after the silhouette fit, at 12 views of 256 x 192 px (~1.1 mm per pixel)
    assert _registration_ok(err), (err.mean(), err.max())
    sil = reg["silhouette"]
    # measured 0.88, 0.98 px; broken: test_a_tipped_registration_fails_the_silhouette_bound
    assert _silhouette_ok(sil), sil
    obj = MeshData.load_npz(out / "object.npz")
    assert abs(float(obj.vertices[:, 2].min())) < 1e-6
    assert len(obj.faces) <= 12000
    # measured 79.93 mm (0.07 mm short; the placed model's z extent, _height_mm, agrees to 1e-6 mm); bound 0.3 mm
    # (was 1.0 mm, which a 1% scale misread passed): broken variants in test_a_broken_registration_fails_the_bound
    assert abs(m["object_height_mm"] - HEIGHT * 1e3) < 0.3


# broken registrations: what a wrong yaw, a one-pixel slip or a misread unit would give
BROKEN_REGISTRATION = {"turned 2 degrees about the vertical": ("yaw", 2.0),
                       "tipped 3 degrees (a wrong up axis, nearly)": ("tip", 3.0),
                       "shifted 1 mm (a pixel) sideways": ("shift", 1e-3),
                       "scaled 1% (a unit or scale misread)": ("scale", 1.01)}


@pytest.mark.parametrize("broken", list(BROKEN_REGISTRATION))
def test_a_broken_registration_fails_the_bound(geometry_run, photo_capture, broken):
    """A test of the test (tests/broken.py): the stage's registration, broken, misses the vertex bound above
    (measured mean / max: 0.87 / 1.62 mm turned, 1.82 / 4.18 mm tipped, 0.94 / 1.12 mm shifted, 0.52 / 0.92 mm
    scaled; bound 0.4 / 0.8); tipped and scaled miss the height bound too (80.78 / 80.73 mm against 80 +- 0.3)."""
    from scipy.spatial.transform import Rotation

    _, m = geometry_run
    w = np.asarray(m["registration"]["world_from_model"], np.float64)
    kind, amount = BROKEN_REGISTRATION[broken]
    b = np.eye(4)  # applied in the world after the registration, about the object's vertical axis
    truth = MeshData.load_npz(photo_capture.truth / "object.npz").vertices.astype(np.float64)
    c = truth.mean(axis=0) * [1, 1, 0]
    if kind == "yaw":
        b[:3, :3] = Rotation.from_euler("z", amount, degrees=True).as_matrix()
        b[:3, 3] = c - b[:3, :3] @ c
    elif kind == "tip":
        b[:3, :3] = Rotation.from_euler("x", amount, degrees=True).as_matrix()
        b[:3, 3] = c - b[:3, :3] @ c
    elif kind == "shift":
        b[0, 3] = amount
    else:
        b[:3, :3] *= amount
        b[:3, 3] = c - amount * c
    err = _registration_error(b @ w, photo_capture)
    assert not _registration_ok(err), (err.mean(), err.max())
    if kind in ("tip", "scale"):  # and the height bound of test_known_shape_registration
        height = _height_mm(b @ w, photo_capture)
        assert not abs(height - HEIGHT * 1e3) < 0.3, height


def _silhouette_ok(sil: dict) -> bool:
    return bool(sil["agree_fraction"] > 0.7 and sil["rms_px"] < 1.5)


def test_a_tipped_registration_fails_the_silhouette_bound(geometry_run, photo_capture):
    """A test of the test (tests/broken.py): the silhouette bound of test_known_shape_registration, on the fit's
    statistics taken at a given pose (one Gauss-Newton step: the residuals before it moves, mask offset 0), passes at
    the stage's pose (measured agreement 0.83, 1.17 px) and misses at the pose tipped 3 degrees (0.69, 1.75 px).
    Not variants: turned 2 degrees (0.82, 1.24 px) and shifted 1 mm (0.81, 1.33 px) pass it, as the vertex bound
    does not; the silhouettes see a pixel's slip only as a fraction of the rim."""
    from scipy.spatial.transform import Rotation

    from objcam.geometry.register import Registration, apply
    from objcam.geometry.silfit import fit
    from objcam.geometry.silhouette import silhouettes, volume_roi
    from objcam.geometry.views import load_views
    from objcam.schemas.capture import CaptureManifest
    from objcam.stages import geometry

    _, m = geometry_run
    params = geometry.Params()
    views = load_views(photo_capture.ingest, photo_capture.sfm, params.min_views)
    cams = [v.camera for v in views]
    lo, hi = geometry._volume(CaptureManifest.load(photo_capture.capture), params)
    masks = silhouettes(views, params.silhouette, progress=False, rois=[volume_roi(c, lo, hi) for c in cams])
    one_step = params.registration.silhouette_fit.model_copy(update={"iterations": 1})
    known = load_mesh(photo_capture.capture / "object.ply")
    w = np.asarray(m["registration"]["world_from_model"], np.float64)
    c = MeshData.load_npz(photo_capture.truth / "object.npz").vertices.astype(np.float64).mean(axis=0) * [1, 1, 0]
    tip = np.eye(4)  # about the object's base centre, as in test_a_broken_registration_fails_the_bound
    tip[:3, :3] = Rotation.from_euler("x", 3.0, degrees=True).as_matrix()
    tip[:3, 3] = c - tip[:3, :3] @ c

    def sil_at(world_from_model: np.ndarray) -> dict:
        reg = Registration.model_validate({**m["registration"], "world_from_model": world_from_model.tolist()})
        return fit(apply(known, reg), masks, cams, one_step, [v.image for v in views]).model_dump()

    assert _silhouette_ok(sil_at(w))
    assert not _silhouette_ok(sil_at(tip @ w))


def test_carved_hull_close_to_truth(geometry_run, photo_capture):
    from objcam.geometry.chamfer import chamfer

    out, m = geometry_run
    hull = MeshData.load_npz(out / "hull.npz")
    truth = MeshData.load_npz(photo_capture.truth / "object.npz")
    ch = chamfer(hull, truth, 30000)
    # a 12-view visual hull from estimated silhouettes at ~1.1 mm per pixel (true masks: 1.34 mm); measured
    # 1.22 mm = 1.5% of height
    assert ch.mean < 0.02 * HEIGHT, ch
    assert not m["hull_touches_volume"]
    assert m["ambiguous_pixels"] > 0 and abs(m["outline_offset_px"]) < 1.0
    masks = sorted((out / "masks").glob("*.png"))
    assert len(masks) == SMALL["n_views"]


@pytest.mark.parametrize("broken", ["shifted 4 mm", "grown 4%", "its convex hull"])
def test_a_broken_hull_fails_the_bound(geometry_run, photo_capture, broken):
    """A test of the test (tests/broken.py): the stage's hull moved by four pixels, grown by 4% about its base
    (silhouettes two pixels too generous) or replaced by its convex hull (the concavities no view carved) misses
    the 1.6 mm Chamfer bound above (measured 1.98, 1.97 and 3.89 mm). What it cannot see: a hull moved by two
    pixels scores 1.47 mm and by three 1.71 mm (a fat hull's mean distance hardly grows with a slip); the
    registration bound above catches a one-pixel slip of the registered model."""
    import trimesh

    from objcam.geometry.chamfer import chamfer

    out, _ = geometry_run
    hull = MeshData.load_npz(out / "hull.npz")
    v = hull.vertices.astype(np.float64)
    if broken.startswith("shifted"):
        v = v + [4e-3, 0, 0]
        bad = MeshData(v.astype(np.float32), hull.faces)
    elif broken.startswith("grown"):
        c = v.mean(axis=0) * [1, 1, 0]
        bad = MeshData((c + 1.04 * (v - c)).astype(np.float32), hull.faces)
    else:
        cv = trimesh.Trimesh(v, hull.faces.astype(np.int64), process=False).convex_hull
        bad = MeshData(np.asarray(cv.vertices, np.float32), np.asarray(cv.faces, np.uint32))
    ch = chamfer(bad, MeshData.load_npz(photo_capture.truth / "object.npz"), 30000)
    print(broken, ch.mean * 1e3)
    assert not ch.mean < 0.02 * HEIGHT, ch


@pytest.fixture(scope="module")
def silhouette_masks(photo_capture):
    """(true masks, estimated (mask, known) pairs) of the first 6 views."""
    from objcam.geometry.raycast import object_masks
    from objcam.geometry.silhouette import silhouettes
    from objcam.geometry.views import load_views

    views = load_views(photo_capture.ingest, photo_capture.sfm)[:6]
    truth = MeshData.load_npz(photo_capture.truth / "object.npz")
    true = object_masks(truth, [v.camera for v in views])
    est = silhouettes(load_views(photo_capture.ingest, photo_capture.sfm), progress=False)[:6]
    return true, est


def _missed_extra(true, est) -> tuple[float, float]:
    tot = sum(t.sum() for t in true)
    missed = sum((t & ~(m & k)).sum() for t, (m, k) in zip(true, est)) / tot
    extra = sum(((m & k) & ~t).sum() for t, (m, k) in zip(true, est)) / tot
    return float(missed), float(extra)


def test_silhouettes_against_true_masks(silhouette_masks):
    missed, extra = _missed_extra(*silhouette_masks)
    # generous masks: few object pixels missed (measured 2%: the lowest millimetres; 9% before the dissimilarity
    # took the larger of its two ways), false object pixels scattered over the noisy 16-spp paper (measured 71%
    # of the object's area; cut away by the other views)
    assert missed < 0.05 and extra < 1.0, (missed, extra)


@pytest.mark.parametrize("broken", ["eroded 2 px", "every pixel object"])
def test_broken_silhouettes_fail_the_bounds(silhouette_masks, broken):
    """A test of the test (tests/broken.py): the estimated masks eroded by two pixels (a tight segmentation) miss
    too much of the object, and a mask that calls everything object claims far too much (measured: 15.7% missed;
    14 x the object's area extra)."""
    import cv2

    true, est = silhouette_masks
    if broken.startswith("eroded"):
        bad = [(cv2.erode((m & k).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0, k) for m, k in est]
    else:
        bad = [(np.ones_like(m), np.ones_like(k)) for m, k in est]
    missed, extra = _missed_extra(true, bad)
    print(broken, missed, extra)
    assert not (missed < 0.05 and extra < 1.0), (missed, extra)


# --------------------------------------------------------------------------------------------- the modules


def test_plane_fit_recovers_tilted_plane_with_outliers():
    from scipy.spatial.transform import Rotation

    from objcam.geometry.plane import fit_plane

    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-0.2, 0.2, (2000, 2)), rng.normal(0, 1e-4, 2000)]
    p[:200, 2] += rng.uniform(0.005, 0.05, 200)  # points on the object: gross outliers
    rot = Rotation.from_euler("x", 2.0, degrees=True)
    p = rot.apply(p) + [0, 0, 0.003]
    fit = fit_plane(p, threshold=1e-3)
    assert fit.n_inliers == pytest.approx(1800, abs=10)
    assert fit.tilt_deg == pytest.approx(2.0, abs=0.01)
    assert fit.offset_mm == pytest.approx(3.0, abs=0.02)
    assert fit.rms_mm == pytest.approx(0.1, abs=0.01)
    # a test of the test: an inlier threshold so loose that the object's points count (a least-squares fit through
    # the outliers) misses the offset and RMS bounds (measured 5.7 mm offset, 9.1 mm RMS)
    bad = fit_plane(p, threshold=1.0)
    print("loose threshold", bad.n_inliers, bad.tilt_deg, bad.offset_mm, bad.rms_mm)
    assert not (abs(bad.offset_mm - 3.0) <= 0.02 and abs(bad.rms_mm - 0.1) <= 0.01), bad


def test_surface_nets_sphere():
    from objcam.geometry.chamfer import sample_surface
    from objcam.geometry.surface import surface_nets

    h, r = 0.002, 0.03
    g = np.arange(-0.04, 0.04 + h / 2, h)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    mesh = surface_nets(r - np.sqrt(x**2 + y**2 + z**2), np.array([g[0]] * 3), h)
    d = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(d - r).max() < 0.1 * h  # sub-voxel: one vertex per cell at the mean of its edge crossings
    p, n = sample_surface(mesh, 2000, with_normals=True)
    assert np.mean(np.einsum("ij,ij->i", p, n) > 0) > 0.99  # outward-facing triangles
    # tests of the test: vertices at their cells' centres (no sub-voxel placement), and the faces wound the
    # other way, miss the bounds (measured 0.83 h off the sphere; inward normals)
    snapped = (np.floor((mesh.vertices - g[0]) / h) + 0.5) * h + g[0]
    print("snapped", np.abs(np.linalg.norm(snapped, axis=1) - r).max() / h)
    assert not np.abs(np.linalg.norm(snapped, axis=1) - r).max() < 0.1 * h
    p, n = sample_surface(MeshData(mesh.vertices, mesh.faces[:, ::-1].copy()), 2000, with_normals=True)
    assert not np.mean(np.einsum("ij,ij->i", p, n) > 0) > 0.99


def test_unit_detection_and_implausible_model():
    from objcam.geometry.register import detect_unit
    from objcam.synth.assets import icosphere

    v, f = icosphere(2)
    hull = MeshData((v * 0.05).astype(np.float32), f.astype(np.uint32))
    assert detect_unit(MeshData((v * 51).astype(np.float32), f), hull, 1.6)[0] == "mm"
    assert detect_unit(MeshData((v * 5.1).astype(np.float32), f), hull, 1.6)[0] == "cm"
    assert detect_unit(MeshData((v * 0.049).astype(np.float32), f), hull, 1.6)[0] == "m"
    with pytest.raises(InputError, match="no unit"):
        detect_unit(MeshData((v * 0.3).astype(np.float32), f), hull, 1.6)  # 30 cm model, 5 cm object


def test_chamfer_of_offset_sphere():
    from objcam.geometry.chamfer import chamfer
    from objcam.synth.assets import icosphere

    v, f = icosphere(4)
    a = MeshData((v * 0.05).astype(np.float32), f.astype(np.uint32))
    b = MeshData((v * 0.051).astype(np.float32), f.astype(np.uint32))
    # nearest-sample distances overestimate by about spacing^2 / (2 d): measured 1.06 mm for a 1 mm offset
    assert _chamfer_ok(chamfer(a, b, 20000).mean)


def _chamfer_ok(mean_m: float) -> bool:
    """test_chamfer_of_offset_sphere's bound: 1.05 mm within 3%."""
    return mean_m == pytest.approx(0.00105, rel=0.03)


# broken measurements of the 1 mm offset: the outer sphere 10% further out, the same sphere moved 1 mm instead of
# grown (a mean distance near 0.5 mm, not 1), and too few samples (the nearest-sample overestimate grows)
BROKEN_CHAMFER = {"offset 1.1 mm": ("radius", 0.0511), "moved 1 mm, not grown": ("moved", 1e-3),
                  "1,000 samples": ("samples", 1000)}


@pytest.mark.parametrize("broken", list(BROKEN_CHAMFER))
def test_a_broken_chamfer_fails_the_bound(broken):
    """A test of the test (tests/broken.py): each broken measurement misses the 3% bound above (measured 1.15,
    0.63 and 1.80 mm against 1.05)."""
    from objcam.geometry.chamfer import chamfer
    from objcam.synth.assets import icosphere

    v, f = icosphere(4)
    kind, amount = BROKEN_CHAMFER[broken]
    a = MeshData((v * 0.05).astype(np.float32), f.astype(np.uint32))
    b, n = MeshData((v * 0.051).astype(np.float32), f.astype(np.uint32)), 20000
    if kind == "radius":
        b = MeshData((v * amount).astype(np.float32), f.astype(np.uint32))
    elif kind == "moved":
        b = MeshData((v * 0.05 + [amount, 0, 0]).astype(np.float32), f.astype(np.uint32))
    else:
        n = int(amount)
    got = chamfer(a, b, n).mean
    print(broken, got * 1e3)
    assert not _chamfer_ok(got), got


# ------------------------------------------------------------------------------------------------ bad input


def test_too_few_registered_views(photo_capture, tmp_path):
    from objcam.stages import geometry

    sfm = tmp_path / "sfm"
    shutil.copytree(photo_capture.sfm, sfm)
    for p in sorted((sfm / "cameras" / "views").glob("*.json"))[3:]:
        p.unlink()  # SfM registered only 3 of 12
    with pytest.raises(InputError, match=r"only 3/12 views are registered") as e:
        geometry.run(StageInputs(capture=photo_capture.capture, out=tmp_path / "out", quiet=True,
                                 upstream={"ingest": photo_capture.ingest, "sfm": sfm}), geometry.Params())
    assert "\n" not in str(e.value) and "cameras" in str(e.value)


def test_object_mesh_that_does_not_load(photo_capture, tmp_path):
    from objcam.stages import geometry

    cap = tmp_path / "capture"
    shutil.copytree(photo_capture.capture, cap)
    (cap / "object.ply").write_text("ply\nthis is not a mesh\n")
    with pytest.raises(InputError, match="object.ply") as e:
        geometry.run(StageInputs(capture=cap, out=tmp_path / "out", quiet=True,
                                 upstream={"ingest": photo_capture.ingest, "sfm": photo_capture.sfm}),
                     geometry.Params())
    assert "\n" not in str(e.value) and "fix:" in str(e.value)


def test_geometry_json_written(geometry_run):
    out, m = geometry_run
    data = json.loads((out / "geometry.json").read_text())
    assert data["object_source"].startswith("known shape") and data["views"] == SMALL["n_views"]
    sup = MeshData.load_npz(out / "support.npz")
    assert np.all(sup.vertices[:, 2] == 0)


def _run_geometry(capture, upstream, out, **params):
    from objcam.stages import geometry

    out.mkdir(parents=True, exist_ok=True)
    return geometry.run(StageInputs(capture=capture, out=out, quiet=True, upstream=upstream),
                        geometry.Params(**params))


def test_empty_and_non_manifold_meshes_refused(photo_capture, tmp_path):
    from objcam.synth.assets import write_ply

    up = {"ingest": photo_capture.ingest, "sfm": photo_capture.sfm}
    cap = tmp_path / "capture"
    shutil.copytree(photo_capture.capture, cap)
    good = load_mesh(cap / "object.ply")
    # no triangles
    (cap / "object.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                    "property float z\nelement face 0\nproperty list uchar int vertex_indices\n"
                                    "end_header\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match="no triangles") as e:
        _run_geometry(cap, up, tmp_path / "out1")
    assert "\n" not in str(e.value) and not any((tmp_path / "out1").iterdir())
    # a fin glued onto one of the model's edges: three faces share it
    a, b = good.faces[0][:2]
    v = np.r_[good.vertices, [[0.0, 0.0, 500.0]]].astype(np.float32)
    f = np.r_[good.faces, [[a, b, len(good.vertices)]]].astype(np.uint32)
    write_ply(cap / "object.ply", v, f)
    with pytest.raises(InputError, match="not manifold: 1 of") as e:
        _run_geometry(cap, up, tmp_path / "out2")
    assert "fix:" in str(e.value) and not any((tmp_path / "out2").iterdir())


def test_too_few_support_points(photo_capture, tmp_path):
    from objcam.image_io import save_npz

    sfm = tmp_path / "sfm"
    shutil.copytree(photo_capture.sfm, sfm)
    save_npz(sfm / "points.npz", xyz=np.zeros((5, 3)), rgb=np.zeros((5, 3), np.uint8), error=np.zeros(5),
             track=np.zeros(5, np.int64))
    with pytest.raises(InputError, match=r"only 5 points lie near the support plane") as e:
        _run_geometry(photo_capture.capture, {"ingest": photo_capture.ingest, "sfm": sfm}, tmp_path / "out",
                      board_corners=False)
    assert "points.npz" in str(e.value) and not any((tmp_path / "out").iterdir())


def test_wrong_shape_refused(geometry_run, photo_capture):
    """A model of the right size but the wrong shape (an ellipsoid in mm) is refused: its outline lies off the
    photographed silhouettes (measured 39% on them, against 88% for the bunny)."""
    import cv2

    from objcam.geometry.register import RegisterParams, apply, register, with_silhouette_fit
    from objcam.geometry.silfit import fit
    from objcam.geometry.views import load_views
    from objcam.synth.assets import icosphere

    out, _ = geometry_run
    hull = MeshData.load_npz(out / "hull.npz")
    views = load_views(photo_capture.ingest, photo_capture.sfm)
    masks = []
    for v in views:
        m = cv2.imread(str(out / "masks" / f"{v.name}.png"), cv2.IMREAD_GRAYSCALE)
        masks.append((m == 255, m != 128))
    s, f = icosphere(3)
    model = MeshData((s * [40.0, 25.0, 40.0]).astype(np.float32), f.astype(np.uint32))
    with pytest.raises(InputError, match="does not match the photographed object") as e:
        reg = register(model, hull, RegisterParams(yaw_steps=8))
        sf = fit(apply(model, reg), masks, [v.camera for v in views], images=[v.image for v in views])
        with_silhouette_fit(reg, sf, RegisterParams().min_silhouette_agreement)
    assert "\n" not in str(e.value)
