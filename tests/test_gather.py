"""Indirect light by the node gather (objcam.transport.gather): its quadrature against the analytic view of a
sphere, its node grid, and its columns against Mitsuba's path tracer (light of two and more bounces)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from objcam.scene import SceneDescription
from objcam.transport.auto import indirect_render
from objcam.transport.gather import Gather, GatherIndirect, GatherSettings, surface_nodes
from objcam.transport.geometry import SceneGeometry, primary_samples
from objcam.transport.path import PathRenderer
from tests.test_transport import ENV_H, R, SIZE, _write_artifact


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gather")
    cam = _write_artifact(folder)
    desc = SceneDescription.model_validate_json((folder / "scene.json").read_text())
    geo = SceneGeometry.load(desc, folder, env_height=ENV_H)
    s = primary_samples(geo, cam, 1, 16, np.arange(SIZE * SIZE), SIZE, seed=0)
    return geo, cam, s.subset(s.hit.any(axis=1))


@pytest.mark.parametrize("how", ["_directions", "directions_dr"])
def test_directions_integrate_the_view_of_the_sphere(scene, how):
    """sum of the ray weights that hit the object's bounding sphere = (1/pi) int_cone cos = sin^2(a) cos(b) for a
    sphere of angular radius a whose centre is b from the normal (wholly above the horizon), for the three ways a
    receiver samples: the cone alone, the cone plus outside-cone cosine rays, the plain hemisphere. Both the numpy
    directions and the Dr.Jit rays the gather traces (Gather._rays, float32)."""
    geo, _, _ = scene
    nodes = surface_nodes(geo, GatherSettings())
    g = Gather(geo, nodes)
    directions = getattr(g, how)
    c, rad = g.centre, g.radius
    # receivers on the plane at distance 3 R from the centre's foot, normals up or tilted towards the sphere
    pos = np.array([[3 * R, 0.0, 0.0], [0.0, -4 * R, 0.0], [2.5 * R, 2.5 * R, 0.0]]) + np.array([c[0], c[1], 0])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.3, 0.95], [-0.2, -0.2, 0.96]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    vec = c - pos
    dist = np.linalg.norm(vec, axis=1)
    want = (rad / dist) ** 2 * np.einsum("px,px->p", vec / dist[:, None], nrm)
    keys = np.arange(3)
    for on_plane, n_rays, tol in ((np.ones(3, bool), 256, 2e-3), (np.zeros(3, bool), 512, 5e-3)):
        d, wt = directions(pos, nrm, keys, n_rays, on_plane)
        hits = np.einsum("prx,px->pr", d, vec / dist[:, None]) > np.sqrt(1 - (rad / dist[:, None]) ** 2)
        got = (wt * hits).sum(axis=1)
        assert np.allclose(got, want, rtol=tol), (on_plane[0], got, want)
    # inside the sphere every receiver samples the cosine-weighted hemisphere: the weights sum to 1
    d, wt = directions(c[None] + 0.1 * rad, np.array([[0.0, 0.0, 1.0]]), keys[:1], 64, np.zeros(1, bool))
    assert wt.sum() == pytest.approx(1.0) and np.all(d[0] @ [0, 0, 1] > 0)


def test_dr_rays_are_the_numpy_directions(scene):
    """Gather._rays (what the gather traces, float32 in Dr.Jit) against Gather._directions (float64 numpy) on the
    scene's own receivers, every sampling kind: the same directions to float32 precision, the same weights, and
    the same rays dropped (weight 0). Measured: directions within 8e-6, weights within 3e-7 relative."""
    from objcam.transport.gather import _receivers

    geo, _, s = scene
    g = Gather(geo, surface_nodes(geo, GatherSettings()))
    pos, nrm, _, _, keys, on_obj, on_plane, _ = _receivers(s, geo)
    inside = np.linalg.norm(pos - g.centre, axis=1) <= g.radius
    assert on_plane.any() and inside.any() and (~inside).any()  # cone, cosine rays, and (no plane flag) split
    for flags, n_rays in ((on_plane, 8), (np.zeros_like(on_plane), 16), (on_plane, 7)):
        d0, w0 = g._directions(pos, nrm, keys, n_rays, flags)
        d1, w1 = g.directions_dr(pos, nrm, keys, n_rays, flags)
        assert np.abs(d1 - d0).max() < 5e-5
        assert np.abs(w1 - w0).max() < 1e-5 * w0.max()
        assert np.array_equal(w1 > 0, w0 > 0)
    # a test of the test: the shifts of another seed give other directions
    g2 = Gather(geo, g.nodes, seed=1)
    other = g2.directions_dr(pos, nrm, keys, 8, on_plane)[0]
    assert np.abs(other - g._directions(pos, nrm, keys, 8, on_plane)[0]).max() > 0.1


def test_plane_cells_hold_their_points(scene):
    geo, _, _ = scene
    nodes = surface_nodes(geo, GatherSettings(node_points=8, node_shadow_rays=4))
    grid = nodes.grid
    from objcam.transport.gather import _face_normals
    from objcam.transport.mesh_nodes import mesh_nodes

    assert nodes.n_object == mesh_nodes(*_face_normals(geo.object_mesh), 12000)[2] and nodes.n_support == grid.n_cells
    u = np.linspace(0.05, 0.95, 5)
    pts = grid.points(u, u[::-1])
    cells = grid.cell_of(pts.reshape(-1, 2)).reshape(pts.shape[:2])
    assert np.array_equal(cells, np.repeat(np.arange(grid.n_cells)[:, None], 5, axis=1))
    # the grid reaches the plane's farthest corner; cells under the sphere's contact point still exist
    assert grid.edges[-1] >= np.hypot(1.0, 1.0) - 1e-9
    assert (nodes.live >= 0).sum() == nodes.count > 0.9 * (nodes.n_object + nodes.n_support)


@pytest.mark.parametrize("max_depth, max_nodes", [(3, 12000), (6, 12000), (6, 300)])
def test_columns_match_path_traced_indirect_light(scene, max_depth, max_nodes):
    """Per texel, the gathered indirect light of every pixel against path(max_depth) - path(2) rendered with the
    same seed (two seeds, so the renders' own noise is taken out of the error); max_nodes 300: the sphere's 1,280
    faces gathered in clusters."""
    geo, cam, s = scene
    grid_w = 2 * ENV_H
    texels = np.array([1 * grid_w + 3, 2 * grid_w + 9, 3 * grid_w + 14])
    gs = GatherSettings(max_depth=max_depth, rays=256, object_rays=1024, max_mesh_nodes=max_nodes)
    gi = GatherIndirect(geo, s, texels, ENV_H, 1, gs)
    if max_nodes < len(geo.object_mesh.faces):
        assert gi.nodes.n_object < len(geo.object_mesh.faces) / 2
    cols = gi.columns(0, texels.size)[0]
    assert cols.shape == (s.pixel_index.size, texels.size) and np.all(cols >= 0)
    pr = PathRenderer(geo, cam, 1, s.pixel_index, ENV_H)
    spp = 512
    # a test of the test: at max_depth 6 the columns of a gather with one bounce (max_depth 3) miss the bound
    # (measured 32-40%). One bounce short (max_depth 5) is 3-5% off and passes on some scenes: the 5% bound
    # cannot see the last of four bounces
    short = GatherIndirect(geo, s, texels, ENV_H, 1, dataclasses.replace(gs, max_depth=3)) \
        if max_depth == 6 else None
    short_errs, short_sums = [], []
    for b, j in enumerate(texels):
        env = pr.onehot([j])
        r1 = indirect_render(pr, env, spp, max_depth, seed=11, scale=1).mean(axis=1)
        r2 = indirect_render(pr, env, spp, max_depth, seed=12, scale=1).mean(axis=1)
        ref = 0.5 * (r1 + r2)
        noise = np.linalg.norm(r1 - r2) / 2

        def col_err(col):
            return np.sqrt(max(np.linalg.norm(col - ref) ** 2 - noise**2, 0.0)) / np.linalg.norm(ref)

        err = col_err(cols[:, b])
        assert err < 0.05, (j, err, noise / np.linalg.norm(ref))
        assert cols[:, b].sum() == pytest.approx(ref.sum(), rel=0.03)
        if short is not None:
            sc = short.columns(b, b + 1)[0][:, 0]
            short_errs.append(col_err(sc))
            short_sums.append(sc.sum() / ref.sum() - 1)
    assert short is None or max(short_errs) >= 0.05, short_errs
    assert short is None or max(np.abs(short_sums)) >= 0.03, short_sums  # and the column sums' bound
    # deterministic: the same settings give the same columns
    again = GatherIndirect(geo, s, texels, ENV_H, 1, gs).columns(0, texels.size)[0]
    assert np.array_equal(cols, again)
    m = gi.metrics()
    assert m["gather_bounces"] == max_depth - 2 and m["gather_hits"] > 0


def test_face_clusters_keep_sides_apart(scene):
    from objcam.transport.gather import _face_normals
    from objcam.transport.mesh_nodes import face_clusters

    geo, _, _ = scene
    tri, n = _face_normals(geo.object_mesh)
    same, count = face_clusters(tri, n, 10 * len(tri))
    assert count == len(tri) and np.array_equal(same, np.arange(len(tri)))
    node, count = face_clusters(tri, n, 200)
    assert 50 < count <= 400 and node.max() == count - 1
    for j in range(count):  # every cluster's normals lie within 90 degrees of their mean
        m = n[node == j]
        mean = m.sum(axis=0) / np.linalg.norm(m.sum(axis=0))
        assert np.all(m @ mean > 0)


def _unknown_and_known_support(tmp_path, rho_known: float) -> dict:
    """The gather of two small scenes, the support's albedo unknown and known at ``rho_known``: per scene name
    ("unknown", "known") its (M, 2) columns of two texels, the GatherIndirect (keeping its bounce parts) and the
    pixel samples."""
    runs = {}
    for name, sup in (("unknown", None), ("known", (rho_known,) * 3)):
        folder = tmp_path / name
        cam = _write_artifact(folder, sup=sup)
        desc = SceneDescription.model_validate_json((folder / "scene.json").read_text())
        geo = SceneGeometry.load(desc, folder, env_height=ENV_H)
        s = primary_samples(geo, cam, 1, 16, np.arange(SIZE * SIZE), SIZE, seed=0)
        s = s.subset(s.hit.any(axis=1))
        texels = np.array([1 * 2 * ENV_H + 3, 3 * 2 * ENV_H + 14])
        gi = GatherIndirect(geo, s, texels, ENV_H, 1, GatherSettings(rays=64, object_rays=256), keep_parts=True)
        runs[name] = (gi.columns(0, texels.size)[0], gi, s)
    return runs


def test_unknown_support_reflects_with_its_bounce_albedo(tmp_path):
    """A support of unknown albedo is a receiver at albedo 1 (A = diag(rho) A') but lights the object with
    UNKNOWN_BOUNCE_ALBEDO: the columns equal those of the same scene with that albedo known, the support's rows
    divided by it."""
    from objcam.transport.gather import UNKNOWN_BOUNCE_ALBEDO as RHO

    runs = _unknown_and_known_support(tmp_path, RHO)
    (u, _, s), (k, _, _) = runs["unknown"], runs["known"]
    # pixels wholly on the object, wholly on the support (mixed ones are a blend of both rules)
    obj, sup = (s.on_object & s.hit).all(axis=1), (~s.on_object & s.hit).all(axis=1)
    assert np.allclose(u[obj], k[obj], rtol=1e-4, atol=1e-9)
    assert np.allclose(u[sup] * RHO, k[sup], rtol=1e-4, atol=1e-9)
    assert u[obj].sum() > 0 and u[sup].sum() > 0


def test_bounce_parts_redo_the_support_light_for_a_new_albedo(tmp_path):
    """The gather's stored parts give, for a new albedo of the support's cells, the same columns as a gather of
    the scene with that albedo known (bounce_indirect), and bounce_delta moves A' towards them from the albedo
    estimated at the pixels: the cells the camera sees take the estimate over them, the free cells no pixel sees
    their count-weighted mean (issue 29: left at the transport's guess they kept lighting the object with it)."""
    from objcam.transport.gather import UNKNOWN_BOUNCE_ALBEDO as RHO, bounce_delta, bounce_indirect

    NEW = 0.8
    runs = _unknown_and_known_support(tmp_path, NEW)
    u, gi, s = runs["unknown"]
    k = runs["known"][0]
    parts = gi.bounce_parts()
    obj = (s.on_object & s.hit).all(axis=1)
    sup = (~s.on_object & s.hit).all(axis=1)
    free = parts["node_unknown"]
    n_obj_live = int((gi.nodes.live[: gi.nodes.n_object] >= 0).sum())  # the object's live nodes' rows come first
    assert free.sum() > 0 and not free[:n_obj_live].any() and free[n_obj_live:].all()
    # unchanged albedo: the stored parts reproduce the columns
    np.testing.assert_allclose(bounce_indirect(parts, np.ones(free.size)), u, rtol=1e-5, atol=1e-9)
    # every support cell at NEW: the columns of the scene whose support albedo is NEW (its rows: receiver 1)
    scale = np.where(free, NEW / RHO, 1.0)
    got = bounce_indirect(parts, scale)
    assert np.allclose(got[obj], k[obj], rtol=1e-4, atol=1e-9)
    assert np.allclose(got[sup] * NEW, k[sup], rtol=1e-4, atol=1e-9)
    # from an albedo estimate at the pixels: the seen cells move, A' moves towards the known scene's
    rows = np.arange(s.pixel_index.size)
    same, info0 = bounce_delta(parts, np.full((rows.size, 3), RHO), rows)
    assert info0["cells_updated"] > 0 and np.abs(same).max() < 1e-6 * np.abs(u).max()
    dA, info = bounce_delta(parts, np.full((rows.size, 3), NEW), rows)
    assert info["cells_updated"] > 0 and info["cell_albedo_after"] == pytest.approx(NEW)
    assert info["cells_unseen_filled"] > 0 and info["unseen_cell_albedo"] == pytest.approx(NEW)
    want = (k - u)[obj]

    def frac(d: np.ndarray) -> float:  # the part of the known scene's change of A' on the object that d makes
        return float((d[obj] * want).sum() / (want * want).sum())

    # every free cell now at NEW: the whole change (measured 1.000)
    assert abs(frac(dA) - 1) < 0.02, frac(dA)
    # the broken variant (the behaviour before issue 29): only the cells a pixel sees updated, the others left at
    # the guess; this camera sees the part of the plane nearest the sphere, not all that lights it (measured 0.39)
    seen = np.zeros(free.size, bool)
    seen[parts["pixel_node"][rows][parts["pixel_node"][rows] >= 0]] = True
    only_seen = bounce_indirect(parts, np.where(free & seen, NEW / RHO, 1.0)) - u
    assert not abs(frac(only_seen) - 1) < 0.02, frac(only_seen)
    # an object of unknown albedo (its nodes made free here): the pixels that see it update its nodes, the unseen
    # ones (its far side) take the seen object nodes' mean, the support's unseen cells the support's; each from its
    # own surface (issue 23: A' then reflects every surface at the albedo the solve writes). Broken variant: one mean
    # over both surfaces for every unseen node (i29's first fill), which gives the support's cells the object's
    # albedo in part and misses the support's value
    n_obj_live = int((gi.nodes.live[: gi.nodes.n_object] >= 0).sum())
    po = parts["pixel_object_node"][rows]
    assert (po[obj] >= 0).all() and (po[obj] < n_obj_live).all() and (po[sup] < 0).all()
    assert parts["node_object"][:n_obj_live].all() and not parts["node_object"][n_obj_live:].any()
    both = dict(parts, node_unknown=parts["node_unknown"] | parts["node_object"])
    OBJ = 0.3
    on_obj = (po >= 0) & (parts["pixel_node"][rows] < 0)  # pixels whose estimate goes to an object node
    est = np.where(on_obj[:, None], OBJ, NEW) * np.ones((rows.size, 3))
    _, info2 = bounce_delta(both, est, rows)
    assert info2["object_nodes_updated"] > 0 and info2["object_albedo_after"] == pytest.approx(OBJ, rel=0.05)
    assert info2["object_nodes_unseen_filled"] > 0 and info2["unseen_object_albedo"] == pytest.approx(OBJ, rel=0.05)
    assert info2["unseen_cell_albedo"] == pytest.approx(NEW, rel=0.02)
    pooled = float(np.mean(np.where(on_obj, OBJ, NEW)[(po >= 0) | (parts["pixel_node"][rows] >= 0)]))  # one fill
    assert not pooled == pytest.approx(NEW, rel=0.02), pooled
