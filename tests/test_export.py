"""`objcam export` (issue 23): the exported Mitsuba scene renders the solve's prediction, the meshes load in
trimesh and pymeshlab with objcam's vertex counts, the cameras round-trip through COLMAP text (read by pycolmap)
and transforms.json, the envmap files hold the solve's envmap."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from objcam.camera import Camera, look_at
from objcam.image_io import read_exr
from objcam.pipeline.cli import main

SIZE = 40  # target pixels per side: downsample 1, so the prediction has the render's size


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path]:
    """A small synthetic capture (a sphere on a checker-textured plane under courtyard, direct light only) run
    through solve and exported."""
    from objcam.synth.capture import SynthParams, synthesize

    root = tmp_path_factory.mktemp("export")
    cap = root / "cap"
    synthesize(cap, SynthParams(object="sphere", object_height=0.04, envmap="courtyard", envmap_height=16,
                                cameras=[{"width": SIZE, "height": SIZE, "distance": 0.25, "elevation_deg": 55.0}],
                                support_albedo="checker", texture_size=64, texture_extent=0.3, spp=64,
                                max_depth=2, noise=False))
    sets = ["transport.env_height=8", "transport.model=direct", "solve.prior=smooth"]
    assert main(["run", str(cap), "-q", "--until", "solve", *[a for s in sets for a in ("--set", s)]]) == 0
    out = root / "out"
    assert main(["export", str(cap), str(out), "--upsample", "2"]) == 0
    return cap, out


def _bias(mi, scene, pred: np.ndarray, spp: int) -> tuple[float, float, float]:
    """(relative L2, its Monte Carlo noise, the bias beyond that noise) of ``scene``'s render against the
    prediction ``pred`` (H, W, 3) over the pixels it predicts; two independent halves give the noise."""
    return _bias_of([np.asarray(mi.render(scene, seed=s, spp=spp), np.float64)[..., :3] for s in (1, 2)], pred)


def _bias_of(halves: list[np.ndarray], pred: np.ndarray) -> tuple[float, float, float]:
    """_bias from two independent renders ``halves`` (each (H, W, 3))."""
    render = (halves[0] + halves[1]) / 2
    used = np.any(pred != 0, axis=2)
    assert used.mean() > 0.5
    norm = np.linalg.norm(pred[used])
    rel = np.linalg.norm(render[used] - pred[used]) / norm
    noise = np.linalg.norm(halves[0][used] - halves[1][used]) / 2 / norm  # the mean's MC noise
    # E|render - pred|^2 = bias^2 + noise^2: the bias (what the scene gets wrong) is what must stay under 1%
    return rel, noise, float(np.sqrt(max(rel**2 - noise**2, 0.0)))


def test_mitsuba_scene_reproduces_the_prediction(exported):
    """Rendered from the target's camera with Mitsuba's own XML loader, the exported scene matches the solve's
    prediction A x within 1% relative L2 beyond the render's Monte Carlo noise (two independent halves). Broken
    variant, asserted below: the render 3% too bright."""
    from objcam.scene import use_mitsuba

    cap, out = exported
    mi = use_mitsuba()
    rec = json.loads((out / "export.json").read_text())
    assert rec["targets"]["t0"]["max_depth"] == 2 and rec["targets"]["t0"]["downsample"] == 1
    scene = mi.load_file(str(out / "mitsuba" / "t0.xml"))
    pred = read_exr(cap / "objcam" / "solve" / "t0" / "prediction.exr")[..., :3].astype(np.float64)
    halves = [np.asarray(mi.render(scene, seed=s, spp=4096), np.float64)[..., :3] for s in (1, 2)]
    rel, noise, bias = _bias_of(halves, pred)
    print(f"relative L2 {rel:.4f}, Monte Carlo noise {noise:.4f}, bias {bias:.4f}")
    assert bias < 0.01 and noise < 0.01, (rel, noise, bias)
    # a test of the test (tests/broken.py): a scene 3% too bright (an envmap scale slip) misses it (measured: bias
    # 0.0067; 3% too bright 0.030)
    too_bright = _bias_of(halves, pred / 1.03)
    assert too_bright[2] >= 0.01, too_bright


def test_meshes_load_with_objcams_vertex_counts(exported):
    import pymeshlab
    import trimesh

    from objcam.scene import MeshData

    cap, out = exported
    for name in ("object", "support"):
        mesh = MeshData.load_npz(cap / "objcam" / "scene" / f"{name}.npz")
        for ext in ("ply", "obj", "glb"):
            tm = trimesh.load(out / "meshes" / f"{name}.{ext}", process=False, force="mesh")
            assert len(tm.vertices) == len(mesh.vertices) and len(tm.faces) == len(mesh.faces), (name, ext)
            assert np.allclose(tm.vertices, mesh.vertices, atol=1e-6)
            if ext == "glb":
                continue  # pymeshlab reads no glTF
            ms = pymeshlab.MeshSet()
            ms.load_new_mesh(str(out / "meshes" / f"{name}.{ext}"))
            assert ms.current_mesh().vertex_number() == len(mesh.vertices), (name, ext)
    # the support's albedo texture travels with its UVs (OpenGL v in the OBJ: 1 - objcam's v)
    sup = MeshData.load_npz(cap / "objcam" / "scene" / "support.npz")
    tm = trimesh.load(out / "meshes" / "support.obj", process=False, force="mesh")
    assert np.allclose(tm.visual.uv, np.column_stack([sup.uv[:, 0], 1 - sup.uv[:, 1]]), atol=1e-6)
    assert "map_Kd support_albedo.png" in (out / "meshes" / "support.mtl").read_text()


def test_cameras_round_trip(exported):
    """COLMAP text read back by pycolmap, and transforms.json, give the target's camera to 1e-9."""
    import pycolmap

    from objcam.export.cameras import read_transforms_json
    from objcam.schemas.artifacts import SceneArtifact

    cap, out = exported
    cam = SceneArtifact.load(cap / "objcam" / "scene").target("t0").camera
    want = np.asarray(cam.world_from_camera)
    rec = pycolmap.Reconstruction(str(out / "colmap"))
    (img,) = rec.images.values()
    assert img.name == "images/t0.png"
    m = np.eye(4)
    m[:3] = img.cam_from_world().inverse().matrix() if callable(img.cam_from_world) else \
        img.cam_from_world.inverse().matrix()
    assert np.allclose(m, want, atol=1e-9)
    c = rec.cameras[img.camera_id]
    fx, fy, cx, cy = c.params
    assert np.allclose([fx, fy, cx - 0.5, cy - 0.5], [cam.fx, cam.fy, cam.cx, cam.cy], atol=1e-9)
    back = read_transforms_json(out / "transforms.json")["t0"]
    assert np.allclose(np.asarray(back.world_from_camera), want, atol=1e-9)
    assert np.allclose([back.fx, back.fy, back.cx, back.cy], [cam.fx, cam.fy, cam.cx, cam.cy], atol=1e-9)


def test_envmap_files(exported):
    """The exported envmaps: the EXR upsampled by repetition, the RGBE file within its 8-bit mantissa. Broken
    variants, asserted below: BGR channels, a map turned one column, 2% too bright."""
    cap, out = exported
    import cv2

    env = read_exr(cap / "objcam" / "solve" / "t0" / "envmap.exr")[..., :3]
    big = read_exr(out / "envmaps" / "t0.exr")[..., :3]
    assert big.shape == (16, 32, 3) and np.array_equal(big[::2, ::2], env) and np.array_equal(big[1::2, 1::2], env)
    hdr = cv2.imread(str(out / "envmaps" / "t0.hdr"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    # RGBE: 8-bit mantissas under one exponent per pixel: within 1% of the pixel's largest channel (the mantissa's
    # step is at most 1/128 of it, 0.78%: the bound has no room to tighten; measured worst 0.74%)
    def rgbe_missed(h: np.ndarray) -> bool:
        return not np.all(np.abs(h - big) <= 0.01 * big.max(axis=2, keepdims=True) + 1e-30)

    assert not rgbe_missed(hdr)
    # a test of the test (tests/broken.py), each missing the bound: the channels left in OpenCV's BGR order
    # (worst 100% of a pixel's largest channel), the map turned one column (light written into the 356 unsolved,
    # zero texels), 2% too bright (an exposure slip, worst 2.0%)
    for broken in (hdr[..., ::-1], np.roll(hdr, 1, axis=1), hdr * 1.02):
        assert rgbe_missed(broken)
    assert read_exr(out / "envmaps" / "t0_mitsuba.exr").shape == (33, 64, 3)


def test_blender_script(exported):
    from objcam.export.blender import script_data

    cap, out = exported
    src = (out / "blender_scene.py").read_text()
    compile(src, "blender_scene.py", "exec")
    data = script_data(out / "blender_scene.py")
    cam = json.loads((cap / "targets" / "t0.json").read_text())
    m = np.asarray(data["cameras"]["t0"]["matrix_world"])
    assert np.allclose(m, np.asarray(cam["world_from_camera"]) @ np.diag([1, -1, -1, 1]), atol=1e-12)
    assert (out / data["envmap"]).is_file() and all((out / m["obj"]).is_file() for m in data["meshes"])
    assert data["render"] == {"max_depth": 2, "samples": 256}
    assert [m["texture"] for m in data["meshes"]] == [None, "meshes/support_albedo.exr"]


def test_export_refuses_a_foreign_folder(exported, tmp_path, capsys):
    cap, _ = exported
    (tmp_path / "mine.txt").write_text("keep")
    assert main(["export", str(cap), str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not empty" in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "mine.txt").read_text() == "keep"


def test_mitsuba_sensor_principal_point():
    """The exported perspective sensor images a small emissive disk where Camera.project says, for an off-centre
    principal point."""
    from objcam.export.mitsuba_xml import sensor_xml
    from objcam.scene import use_mitsuba

    mi = use_mitsuba()
    m = look_at(np.array([0.3, -2.0, 1.5]), np.array([0.1, 0.2, 0.0]))
    cam = Camera(width=80, height=60, fx=90.0, fy=90.0, cx=45.3, cy=25.8, world_from_camera=m.tolist())
    rot = m[:3, :3]
    vv, uu = np.mgrid[0:60, 0:80]
    for pc in (np.array([0.25, -0.2, 2.3]), np.array([-0.3, 0.25, 2.0])):
        p = rot @ pc + m[:3, 3]
        disk = np.eye(4)
        disk[:3, 0], disk[:3, 1], disk[:3, 2], disk[:3, 3] = rot[:, 0] * 0.05, -rot[:, 1] * 0.05, -rot[:, 2] * 0.05, p
        xml = (f'<scene version="3.0.0"><default name="spp" value="256"/><integrator type="path"/>'
               f'{sensor_xml(cam, "c")}'
               '<shape type="disk"><transform name="to_world"><matrix value="'
               + " ".join(map(repr, disk.ravel().tolist()))
               + '"/></transform><emitter type="area"><rgb name="radiance" value="1"/></emitter></shape></scene>')
        y = np.asarray(mi.render(mi.load_string(xml)))[..., 0].astype(np.float64)
        centroid = np.array([(y * uu).sum(), (y * vv).sum()]) / y.sum()
        assert np.all(np.abs(centroid - cam.project(p)) < 0.05), (centroid, cam.project(p))
        # a test of the test (tests/broken.py): a pixel-corner origin (+0.5 px) misses it
        assert not np.all(np.abs(centroid - (cam.project(p) + 0.5)) < 0.05)


def test_run_names_its_results_and_a_copied_capture_stays_fresh(exported, tmp_path, capsys):
    """The end-of-run lines name the envmap file and point to export; a copy of the capture (objcam/ included)
    is as fresh as the original, the report's benchmark input included (keyed by name and content, and shipped
    in the package)."""
    import shutil

    from objcam.pipeline.engine import Pipeline, parse_overrides

    cap, _ = exported
    sets = ["transport.env_height=8", "transport.model=direct", "solve.prior=smooth"]
    assert main(["run", str(cap), "-q", "--until", "solve", *[a for s in sets for a in ("--set", s)]]) == 0
    out = capsys.readouterr().out
    assert f"envmap t0: {cap / 'objcam' / 'solve' / 't0' / 'envmap.exr'}" in " ".join(out.split())
    assert "objcam export" in out
    copy = tmp_path / "elsewhere" / "cap"
    shutil.copytree(cap, copy, symlinks=True)
    a, b = Pipeline(cap, overrides=parse_overrides(sets)), Pipeline(copy, overrides=parse_overrides(sets))
    key_a, parts = a.key("report")
    assert key_a == b.key("report")[0]
    assert set(parts["inputs"]) == {"outside:bench_results.json"}
    assert {r["stage"]: r["state"] for r in b.status()}["solve"] == "done"


@pytest.fixture(scope="module")
def exported_unknown(tmp_path_factory) -> tuple[Path, Path]:
    """The capture of ``exported`` with both albedos unknown (one illumination: the solve's albedo and envmap are
    known only up to scale, which the export must not refit), run through solve and exported."""
    from objcam.synth.capture import SynthParams, synthesize

    root = tmp_path_factory.mktemp("export_unknown")
    cap = root / "cap"
    synthesize(cap, SynthParams(object="sphere", object_height=0.04, envmap="courtyard", envmap_height=16,
                                cameras=[{"width": SIZE, "height": SIZE, "distance": 0.25, "elevation_deg": 55.0}],
                                support_albedo="checker", texture_size=64, texture_extent=0.3, spp=64,
                                max_depth=2, noise=False, object_albedo_known=False, support_albedo_known=False))
    sets = ["transport.env_height=8", "transport.model=direct", "solve.prior=smooth"]
    assert main(["run", str(cap), "-q", "--until", "solve", *[a for s in sets for a in ("--set", s)]]) == 0
    out = root / "out"
    assert main(["export", str(cap), str(out)]) == 0
    return cap, out


def test_baked_albedo_reproduces_the_prediction(exported_unknown, tmp_path):
    """Issue 23: the solve's per-pixel albedo baked into the meshes' textures: the exported scene renders the
    prediction within 1% (measured 0.48% with every albedo unknown, against a 0.42% floor with a known albedo:
    A's own Monte Carlo error). Broken variants that must miss: each baked texture replaced by its mean (what a
    flat albedo would give: 37% with the grey placeholder before the bake), and textures averaged over 8 x 8 texel
    blocks, 2 texels per pixel instead of the rule's 16 (a texel straddling two pixels gives part of one the
    other's albedo)."""
    from objcam.image_io import write_exr
    from objcam.scene import use_mitsuba

    cap, out = exported_unknown
    mi = use_mitsuba()
    rec = json.loads((out / "export.json").read_text())
    assert not any("approximate" in w for w in rec["warnings"]), rec["warnings"]
    for name in ("object", "support"):
        bake = rec["meshes"][name]["bake"]
        assert bake["texels_per_pixel"] > 15 and bake["texels_seen"] > 0.1 * bake["texels_covered"], (name, bake)
    assert "envmap_scale" not in rec["targets"]["t0"]  # the solve's own scale: its albedo travels with it
    xml = (out / "mitsuba" / "t0.xml").read_text()
    pred = read_exr(cap / "objcam" / "solve" / "t0" / "prediction.exr")[..., :3].astype(np.float64)

    def bias(text: str, spp: int) -> tuple[float, float]:
        return _bias(mi, mi.load_string(text.replace('value="../', f'value="{out}/')), pred, spp)[1:]

    noise, good = bias(xml, 4096)
    print(f"baked albedo: bias {good:.4f} (noise {noise:.4f})")
    assert good < 0.01 and noise < 0.01, (good, noise)
    flat = xml
    for name in ("object", "support"):
        mean = read_exr(out / "meshes" / f"{name}_albedo.exr")[..., :3].reshape(-1, 3).mean(axis=0)
        tex = xml[xml.index(f'id="{name}"'):].split("<texture", 1)[1].split("</texture>", 1)[0]
        rgb = ", ".join(repr(float(c)) for c in mean)
        flat = flat.replace(f"<texture{tex}</texture>", f'<rgb name="reflectance" value="{rgb}"/>')
    assert flat.count("<texture") == 0
    coarse = xml
    for name in ("object", "support"):  # 8 x 8 texel blocks: 2 texels per pixel instead of the rule's 16
        img = read_exr(out / "meshes" / f"{name}_albedo.exr")[..., :3]
        h, w = img.shape[0] // 8 * 8, img.shape[1] // 8 * 8
        block = img[:h, :w].reshape(h // 8, 8, w // 8, 8, 3).mean(axis=(1, 3))
        write_exr(tmp_path / f"{name}.exr", np.repeat(np.repeat(block, 8, axis=0), 8, axis=1).astype(np.float32))
        coarse = coarse.replace(f'"../meshes/{name}_albedo.exr"', f'"{tmp_path / name}.exr"')
    broken = {"flat": bias(flat, 256)[1], "coarse": bias(coarse, 1024)[1]}
    print("broken variants' bias", broken)
    assert broken["flat"] > 0.05 and broken["coarse"] > 0.015, broken


def test_baked_meshes_cover_objcams_surfaces(exported_unknown):
    """The re-UV'd meshes (xatlas for the object, the seen rectangle's quads for the support) load with
    export.json's counts and cover the same surfaces as objcam's: the object's faces in objcam's order on its
    vertices, the support's area unchanged."""
    import pymeshlab
    import trimesh

    from objcam.scene import MeshData

    cap, out = exported_unknown
    rec = json.loads((out / "export.json").read_text())
    for name in ("object", "support"):
        mesh = MeshData.load_npz(cap / "objcam" / "scene" / f"{name}.npz")
        tm = trimesh.load(out / "meshes" / f"{name}.obj", process=False, force="mesh")
        assert len(tm.vertices) == rec["meshes"][name]["vertices"] and tm.visual.uv.shape == (len(tm.vertices), 2)
        ms = pymeshlab.MeshSet()
        ms.load_new_mesh(str(out / "meshes" / f"{name}.ply"))
        assert ms.current_mesh().vertex_number() == len(tm.vertices)
        area = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).area
        assert abs(tm.area - area) < 1e-6 * area, (name, tm.area, area)
    obj = MeshData.load_npz(cap / "objcam" / "scene" / "object.npz")
    tm = trimesh.load(out / "meshes" / "object.obj", process=False, force="mesh")
    assert np.allclose(tm.vertices[tm.faces], obj.vertices[obj.faces.astype(np.int64)], atol=1e-6)


def _plane_view(eye: tuple[float, float, float], gain: float, size: int = 32, fx: float = 40.0):
    """An AlbedoView of the support z = 0 (|x|, |y| <= 0.2) seen straight down from ``eye``: each pooled pixel
    holds the true albedo (0.3, and 0.8 where x > 0.15) at its centre's ray, times ``gain`` (a camera's own
    estimate), estimated where the ray meets the support."""
    from objcam.export.bake import AlbedoView

    eye = np.asarray(eye, float)
    cam = Camera(width=size, height=size, fx=fx, fy=fx, cx=(size - 1) / 2, cy=(size - 1) / 2,
                 world_from_camera=look_at(eye, eye * [1, 1, 0]).tolist())
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    o, d = cam.rays(cols, rows)
    hit = o + d * (-o[..., 2:] / d[..., 2:])
    truth = np.where(hit[..., 0] > 0.15, 0.8, 0.3)
    est = (np.abs(hit[..., 0]) <= 0.2) & (np.abs(hit[..., 1]) <= 0.2)
    return AlbedoView(cam, np.repeat((truth * gain)[..., None], 3, axis=2), est)


def test_bake_takes_the_camera_that_sees_each_texel_finest():
    """Two cameras look straight down at the support: camera 1 from 0.6 m (15 mm pooled pixels) frames
    x in [-0.2, 0.14], camera 2 from 0.2 m (5 mm) frames x in [0.02, 0.18], where a patch (x > 0.15) that only
    camera 2 sees has another albedo. Each camera's estimate carries its own gain (0.9 and 1), so the baked texture
    says which camera each texel came from: camera 2's where both see (it sees finer), camera 1's where only it sees,
    and the patch from camera 2. (A bake taking the coarser, the first or the last camera gives 0.27 in the overlap
    in one order of the views.)"""
    from objcam.export.bake import bake_albedo
    from objcam.scene import MeshData

    support = MeshData(np.array([[-0.2, -0.2, 0], [0.2, -0.2, 0], [0.2, 0.2, 0], [-0.2, 0.2, 0]], np.float32),
                       np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
    views = [_plane_view((-0.1, 0.0, 0.6), 0.9), _plane_view((0.1, 0.0, 0.2), 1.0)]
    baked = bake_albedo(support, [], views)
    # in either order (a bake where the first or the last camera wins fails one of them)
    assert np.array_equal(bake_albedo(support, [], views[::-1]).texture, baked.texture)
    tex, v, uv = baked.texture, baked.mesh.vertices, baked.mesh.uv
    # planar UVs: the centre quad of the 3 x 3 grid (vertices 5 and 10 its corners) spans the texture
    (x0, y0), (x1, y1) = v[5, :2], v[10, :2]
    assert np.allclose(uv[[5, 10]], [[0, 1], [1, 0]])
    rows, cols = tex.shape[:2]

    def texels(xa: float, xb: float, ya: float, yb: float) -> np.ndarray:
        ca, cb = (int((x - x0) / (x1 - x0) * cols) for x in (xa, xb))
        ra, rb = (int((y1 - y) / (y1 - y0) * rows) for y in (yb, ya))
        return tex[ra:rb, ca:cb, 0]

    overlap, only1, patch = texels(0.04, 0.12, -0.06, 0.06), texels(-0.18, -0.02, -0.15, 0.15), \
        texels(0.16, 0.175, -0.06, 0.06)
    assert overlap.size > 100 and only1.size > 100 and patch.size > 100
    np.testing.assert_allclose(overlap, 0.3, atol=1e-6)  # camera 2 (camera 1 would give 0.27)
    np.testing.assert_allclose(only1, 0.27, atol=1e-6)  # camera 1
    np.testing.assert_allclose(patch, 0.8, atol=1e-6)  # only camera 2 sees it
    assert baked.record["texels_per_pixel"] == pytest.approx(16.0, rel=0.01)


def test_bounce_scale_rule(tmp_path):
    """objcam.export.scale on a 4 x 4 pooled image: k = the transport's mean bounce albedo under the estimated
    support pixels over the solve's mean albedo there (0.586 / 0.15), and 1 when the scale is pinned, when A
    has no interreflection parts, or when no estimated pixel lies over a support cell."""
    from types import SimpleNamespace

    from PIL import Image

    from objcam.export.scale import bounce_scale
    from objcam.image_io import write_exr

    node = np.full(16, -1)
    node[8:] = [0, 0, 1, 1, 2, 2, 3, 3]  # the lower half over four support cells, the upper half the object
    np.savez(tmp_path / "bounce.npz", node_rho=np.array([[0.5] * 3, [0.7] * 3, [0.5] * 3, [0.7] * 3], np.float32),
             pixel_node=node)
    alb = np.full((4, 4, 3), 0.15, np.float32)
    alb[:2] = 0.9  # the object's albedo takes no part
    alb[3, 3] = 5.0  # left out by the mask
    mask = np.full((4, 4), 255, np.uint8)
    mask[3, 3] = 0
    write_exr(tmp_path / "albedo.exr", alb)
    Image.fromarray(mask).save(tmp_path / "albedo_mask.png")
    tr = SimpleNamespace(has_bounce_parts=True, folder=tmp_path, pixel_index=np.arange(16), image_shape=(4, 4),
                         unknown_albedo=np.ones(16, bool))
    solve = {"albedo": "unknown", "scale_ambiguous": True}
    (tmp_path / "solve.json").write_text(json.dumps(solve))
    b = bounce_scale(tr, tmp_path)
    # the seven estimated pixels over cells 0, 0, 1, 1, 2, 2, 3
    assert b.k == pytest.approx(np.mean([0.5, 0.5, 0.7, 0.7, 0.5, 0.5, 0.7]) / 0.15, rel=1e-6), b.record
    assert b.record["pixels"] == 7
    direct = SimpleNamespace(**{**vars(tr), "has_bounce_parts": False})
    known = SimpleNamespace(**{**vars(tr), "unknown_albedo": np.zeros(16, bool)})
    for change, tr2 in (({"scale_ambiguous": False}, tr), ({}, direct), ({}, known)):
        (tmp_path / "solve.json").write_text(json.dumps({**solve, **change}))
        assert bounce_scale(tr2, tmp_path).k == 1.0, change
