"""Indirect light of every column at once, without path tracing: a deterministic finite-element gather.

The radiance leaving a diffuse surface point q under texel j alone, ``L_j(q) = rho_q / pi int_j V max(0, n.w)``,
is what the direct model computes for a pixel. So the direct light of a set of surface *nodes* (every face of
the object, or clusters of faces beyond ``max_mesh_nodes``, long faces split first: objcam.transport.mesh_nodes;
on a plane support, the cells of a polar grid around the object; on any other support, its faces or face
clusters) is
one more :class:`objcam.transport.direct.DirectModel` run: E (S, N) for S nodes, each averaged over a few points
spread over its area, with the direct model's stratified shadow rays.

A receiver's (a pixel's sub-pixel sample, or a node's point) first-bounce indirect light is its albedo times the
cosine-weighted mean of L over what its hemisphere sees. The rays that estimate that mean do not depend on the
texel, so they are traced once, and each hit is mapped to the node it lands on: a sparse *gather* matrix W with
``L_indirect = W L`` for all N columns at once. More bounces follow on the nodes:
``L = (I + W_QQ + W_QQ^2 + ...) E`` (``max_depth`` - 2 bounces in all, as Mitsuba's path depth counts them), and
the pixels' indirect columns are ``W_PQ L``.

Rays per receiver: inside the object's bounding sphere (the object's own points, the support beneath it)
cosine-distributed over the hemisphere. Outside it the object fills a small cone, which hemisphere rays would
mostly miss, so the hemisphere is partitioned exactly: uniform rays inside the cone to the bounding sphere, plus
cosine-distributed rays whose directions outside the cone count (those inside it are dropped). On a plane support
a receiver on the plane sees nothing outside that cone, so it traces the cone only. Every direction set is a
Sobol sequence with a digital shift per receiver, so the estimate is quasi-Monte Carlo: no texel-dependent noise,
and the same estimate for every column. The rays are generated where they are traced (:meth:`Gather._rays`, Dr.Jit,
float32; :meth:`Gather._directions`: the same rays in numpy, float64, which the tests hold it to).

What it does not model: light reflected by a node varies within the node only through its points' average (a
node is one value per texel), and a receiver's rays are a finite quadrature of its hemisphere (``rays``); both
errors are smooth in the image and shared by neighbouring columns. Measured (bench forest, 128 x 128, 32 x 64):
the defaults are within 0.15% of the image (object pixels) of a 4x-denser gather, A's model error against a
16384-spp path-traced target fell from 0.45% (path-traced correction) to 0.26%, and the indirect part costs
~4 s instead of 15 s. Unknown albedo is rendered as 1 (the transport
convention) where it is the receiver's (A = diag(rho) A' stays exact for the receiving pixel); where a surface of
unknown albedo reflects light onto others it takes its initial estimate (photogrammetry's texture) or
:data:`UNKNOWN_BOUNCE_ALBEDO`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from objcam.dr_memory import padded
from objcam.scene import use_mitsuba
from objcam.threads import cores, parallel_map
from objcam.transport.geometry import PixelSamples, SampleParts, SceneGeometry
from objcam.transport.mesh_nodes import FaceSplit, face_clusters, mesh_nodes
from objcam.transport.pixels import sobol4, to_unit

#: rays per Mitsuba launch of the gather
_BATCH = 1 << 20
#: the albedo a surface of unknown albedo (without an initial estimate) reflects light with, when it lights others:
#: the joint solve's starting albedo (objcam.solvers.joint.DEFAULT_RHO0). A receiver's own albedo stays factored
#: out (A = diag(rho) A'), but the bounce surface's enters the indirect light; rendering it as 1, as the direct
#: part does, made the light the support throws on the object ~2x too bright on a 0.55-albedo support.
UNKNOWN_BOUNCE_ALBEDO = 0.5


@dataclass
class GatherSettings:
    rays: int = 256  # per pixel outside the object's bounding sphere (cone rays; spread over its samples)
    object_rays: int = 2048  # per pixel inside it: the object and the support beneath it (hemisphere rays)
    node_rays: int = 64  # per node (spread over its points)
    node_points: int = 4  # points per node for its direct light (a multiple of node_shadow_rays)
    # per (node, texel) pair, from a hashed half of its points: the gather averages hundreds of nodes' light per
    # pixel (2 instead of 4 moved A by 4% of a new seed's change; bench/results.md, issue 25 session 19)
    node_shadow_rays: int = 2
    max_depth: int = 6  # Mitsuba's path depth: 2 = direct only, 3 = one bounce, ...
    max_mesh_nodes: int = 12000  # a mesh with more faces gets face clusters as nodes (voxel x normal buckets)
    rings_per_octave: int = 8  # plane support: polar grid rings per doubling of the radius
    sectors: int = 64  # plane support: polar grid sectors
    seed: int = 0


@dataclass
class PlaneGrid:
    """Polar cells on the support plane z = 0 around the object: ring i spans radii [edges[i], edges[i + 1]),
    ring 0 is the central disk; ``sectors`` equal sectors per ring (cell = ring * sectors + sector)."""

    centre: np.ndarray  # (2,) metres
    edges: np.ndarray  # (R + 1,) metres, edges[0] = 0
    sectors: int

    @property
    def n_cells(self) -> int:
        return (self.edges.size - 1) * self.sectors

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(P,) cell index of plane points (P, 2); -1 beyond the last ring."""
        d = xy - self.centre
        r = np.hypot(d[:, 0], d[:, 1])
        ring = np.searchsorted(self.edges, r, side="right") - 1
        sec = np.floor(np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi) / (2 * np.pi) * self.sectors).astype(np.int64)
        sec = np.clip(sec, 0, self.sectors - 1)
        return np.where(ring < self.edges.size - 1, ring * self.sectors + sec, -1)

    def points(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(n_cells, k, 2) area-uniform points of every cell for unit coordinates u, v (k,)."""
        ring, sec = np.divmod(np.arange(self.n_cells), self.sectors)
        r0, r1 = self.edges[ring], self.edges[ring + 1]
        r = np.sqrt(r0[:, None] ** 2 + (r1[:, None] ** 2 - r0[:, None] ** 2) * u[None, :])
        phi = 2 * np.pi * (sec[:, None] + v[None, :]) / self.sectors
        return np.stack([self.centre[0] + r * np.cos(phi), self.centre[1] + r * np.sin(phi)], axis=-1)


def plane_grid(geo: SceneGeometry, rings_per_octave: int, sectors: int) -> PlaneGrid:
    """The polar grid for a plane support: from 1/16 of the object's radius (a central disk) to the farthest
    corner of the support rectangle, rings_per_octave rings per doubling of the radius."""
    v = geo.object_mesh.vertices.astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = 0.5 * (lo[:2] + hi[:2])
    rad = 0.5 * float(np.linalg.norm(hi[:2] - lo[:2]))
    x0, x1, y0, y1 = geo.plane
    far = max(np.hypot(x - centre[0], y - centre[1]) for x in (x0, x1) for y in (y0, y1))
    r_min = rad / 16
    n = max(1, int(np.ceil(np.log2(max(far / r_min, 2.0)) * rings_per_octave)))
    edges = np.concatenate([[0.0], r_min * 2.0 ** (np.arange(n + 1) / rings_per_octave)])
    return PlaneGrid(centre, edges, int(sectors))


@dataclass
class Nodes:
    """The surface nodes: the object's faces (or parts or clusters of them) first, then the support's (plane
    cells, or faces or face clusters). ``samples`` holds each live node's points (a PixelSamples, one 'pixel' per
    live node); ``live`` maps a node id to its row in ``samples`` (-1: no point of it exists, e.g. a cell under
    the object)."""

    n_object: int
    n_support: int
    object_face_node: np.ndarray  # (T,) node of each of the object's sub-triangles (its faces, if none is split)
    object_split: FaceSplit  # the object's faces split into those sub-triangles
    support_face_node: np.ndarray | None  # (F_support,) node (after the object's) of each support face; None: grid
    grid: PlaneGrid | None
    samples: PixelSamples
    live: np.ndarray  # (n_object + n_support,) int64
    rho: np.ndarray  # (S_live, 3) mean albedo over each node's points

    @property
    def count(self) -> int:
        return int(self.samples.hit.shape[0])


def _shifts(keys: np.ndarray, salt: int) -> tuple[np.ndarray, np.ndarray]:
    """Two per-key 32-bit digital shifts (a hash of key and salt)."""
    from objcam.transport.direct import _hash_u32

    k = keys.astype(np.uint64) * np.uint64(0x9E3779B1) + np.uint64((0x85EBCA77 * (salt + 1)) & 0xFFFFFFFF)
    return _hash_u32(k).astype(np.uint32), _hash_u32(k + np.uint64(0x632BE59B)).astype(np.uint32)


def _face_normals(mesh) -> tuple[np.ndarray, np.ndarray]:
    v = mesh.vertices.astype(np.float64)
    tri = v[mesh.faces.astype(np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return tri, n


def _node_points(tri: np.ndarray, normals: np.ndarray, face_node: np.ndarray, n_nodes: int, u: np.ndarray,
                 v: np.ndarray, w: np.ndarray):
    """Per node k area-uniform points over its faces: points (S, k, 3), their faces' normals (S, k, 3) and faces
    (S, k), from unit coordinates u, v (point in the face) and w (which face, by area) (k,)."""
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    order = np.argsort(face_node, kind="stable")
    fn = face_node[order]
    cum = np.cumsum(area[order])
    start = np.searchsorted(fn, np.arange(n_nodes))
    end = np.searchsorted(fn, np.arange(n_nodes), side="right")
    base = np.where(start > 0, cum[np.maximum(start - 1, 0)], 0.0)
    total = cum[end - 1] - base
    target = base[:, None] + total[:, None] * w[None, :]
    pick = np.clip(np.searchsorted(cum, target), start[:, None], end[:, None] - 1)
    faces = order[pick]  # (S, k)
    su = np.sqrt(u)[None, :, None]
    t = tri[faces]  # (S, k, 3, 3)
    pts = (1 - su) * t[:, :, 0] + su * (1 - v[None, :, None]) * t[:, :, 1] + su * v[None, :, None] * t[:, :, 2]
    return pts, normals[faces], faces


def surface_nodes(geo: SceneGeometry, s: GatherSettings) -> Nodes:
    """Every node's points, found by casting a short ray onto each point from the side its normal faces (so the
    point's albedo, texture included, is Mitsuba's own and a point hidden inside another surface drops out)."""
    import drjit as dr

    mi = use_mitsuba()
    k = int(s.node_points)
    pts = sobol4(k)
    u, v = to_unit(pts[:, 0]), to_unit(pts[:, 1])
    w = to_unit(pts[:, 2])
    tri_o, n_o = _face_normals(geo.object_mesh)
    split, obj_node, n_obj = mesh_nodes(tri_o, n_o, s.max_mesh_nodes)  # long faces split (objcam.transport.mesh_nodes)
    p_obj, nn_obj, f_sub = _node_points(split.tri, n_o[split.parent], obj_node, n_obj, u, v, w)
    shape_ids = [np.full(n_obj, geo.object_id)]
    prims = [split.parent[f_sub]]
    normals = [nn_obj]
    points = [p_obj]
    grid = None
    sup_node = None
    if geo.plane is not None:
        grid = plane_grid(geo, s.rings_per_octave, s.sectors)
        xy = grid.points(u, v)
        points.append(np.concatenate([xy, np.zeros(xy.shape[:2] + (1,))], axis=2))
        normals.append(np.broadcast_to([0.0, 0.0, 1.0], (grid.n_cells, k, 3)))
        shape_ids.append(np.full(grid.n_cells, geo.support_id))
        prims.append(np.full((grid.n_cells, k), -1))
    else:
        tri_s, n_s = _face_normals(geo.support_mesh)
        sup_node, n_sup = face_clusters(tri_s, n_s, s.max_mesh_nodes)
        p_s, nn_s, f_s = _node_points(tri_s, n_s, sup_node, n_sup, u, v, w)
        points.append(p_s)
        normals.append(nn_s)
        shape_ids.append(np.full(n_sup, geo.support_id))
        prims.append(f_s)
    P = np.concatenate(points)  # (S, k, 3)
    Nn = np.concatenate(normals)  # (S, k, 3)
    sid = np.concatenate(shape_ids)
    prim = np.concatenate(prims)  # (S, k)
    n_nodes = P.shape[0]
    h = 20.0 * geo.eps
    o = (P + h * Nn).reshape(-1, 3).astype(np.float32)
    d = (-Nn).reshape(-1, 3).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(*(padded(o[:, i]) for i in range(3))),  # objcam.dr_memory
                   mi.Vector3f(*(padded(d[:, i]) for i in range(3))))
    ray.maxt = mi.Float(np.float32(2.0 * h))
    si = geo.mi_scene.ray_intersect(ray)
    valid = si.is_valid()
    rho = si.bsdf().eval_diffuse_reflectance(si, valid)
    shp = dr.reinterpret_array(mi.UInt32, si.shape)
    dr.eval(si.p, rho, valid, shp, si.prim_index)
    hit = np.asarray(valid, bool)
    got_sid = np.asarray(shp, np.int64)
    got_prim = np.asarray(si.prim_index, np.int64)
    want_sid = np.repeat(sid, k)
    want_prim = prim.ravel()
    hit &= (got_sid == want_sid) & ((want_prim < 0) | (got_prim == want_prim))
    # a point where two parts touch (a post standing on a seat, coplanar faces) can land and still lie inside the
    # other part: the first surface its outward ray meets is then seen from behind. It drops out like a hidden one
    # (with one node per face such points were a sliver of a large face; in a small node they were half of it)
    out = mi.Ray3f(mi.Point3f(*(padded(o[:, i]) for i in range(3))), mi.Vector3f(*(padded(-d[:, i]) for i in range(3))))
    si_out = geo.mi_scene.ray_intersect(out)
    inside = si_out.is_valid() & (dr.dot(si_out.n, out.d) > 0)
    dr.eval(inside)
    hit &= ~np.asarray(inside, bool)[: hit.size]
    pos = np.asarray(si.p, np.float64).T.reshape(n_nodes, k, 3)
    r = np.asarray(rho, np.float64).T.reshape(n_nodes, k, 3)
    if not (geo.desc.albedo_object.known and geo.desc.albedo_support.known):
        # the albedo the nodes reflect with: unknown ones at their initial estimate or UNKNOWN_BOUNCE_ALBEDO (the
        # same rays on a scene that renders them so; same geometry, so the same hits)
        from objcam.scene import build_mitsuba_scene

        bounce = build_mitsuba_scene(geo.desc, geo.root, unknown_albedo=UNKNOWN_BOUNCE_ALBEDO, initial=True)
        si_b = bounce.ray_intersect(ray)
        rho_b = si_b.bsdf().eval_diffuse_reflectance(si_b, si_b.is_valid())
        dr.eval(rho_b)
        r = np.asarray(rho_b, np.float64).T.reshape(n_nodes, k, 3)
    hit = hit.reshape(n_nodes, k)
    alive = hit.any(axis=1)
    # a point that did not land (hidden, off the support) takes the place of one that did: the direct model then
    # sees only surface points (a miss would count as sky seen along the probe ray)
    first = np.argmax(hit, axis=1)
    fill = ~hit & alive[:, None]
    ni, ki = np.nonzero(fill)
    nrm = np.array(Nn, dtype=np.float64)  # (S, k, 3), writable
    for arr in (pos, r, nrm):
        arr[ni, ki] = arr[ni, first[ni]]
    hit = hit | fill
    live = np.full(n_nodes, -1, np.int64)
    live[alive] = np.arange(int(alive.sum()))
    pos = np.where(hit[..., None], pos + geo.eps * nrm, 0.0)
    r = np.where(hit[..., None], r, 0.0)
    on_obj = np.broadcast_to((sid == geo.object_id)[:, None], (n_nodes, k)) & hit
    unknown = (on_obj & (not geo.desc.albedo_object.known)) | (~on_obj & hit & (not geo.desc.albedo_support.known))
    samples = PixelSamples(np.arange(int(alive.sum()), dtype=np.int64), hit[alive], pos[alive],
                           np.where(hit[..., None], nrm, 0.0)[alive], r[alive], on_obj[alive], unknown[alive],
                           (-nrm)[alive])
    nh = np.maximum(samples.hit.sum(axis=1), 1)[:, None]
    return Nodes(n_obj, n_nodes - n_obj, obj_node, split, sup_node, grid, samples, live,
                 samples.rho.sum(axis=1) / nh)


def _frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (P, 3) orthogonal to unit normals n (P, 3) (Frisvad / Duff et al.)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    bt = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, bt


@dataclass
class GatherStats:
    rays: int = 0
    hits: int = 0
    seconds: float = 0.0


class Gather:
    """Traces the gather rays of receivers and maps their hits to nodes (see the module docstring)."""

    def __init__(self, geo: SceneGeometry, nodes: Nodes, seed: int = 0):
        self.geo, self.nodes, self.seed = geo, nodes, int(seed)
        v = geo.object_mesh.vertices.astype(np.float64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.centre = 0.5 * (lo + hi)
        self.radius = float(np.linalg.norm(v - self.centre, axis=1).max()) * (1 + 1e-6) + 1e-9
        self.stats = GatherStats()

    def _cones(self, pos, on_plane):
        """Each receiver's cone to the object's bounding sphere and which rays it takes: (axis (P, 3) unit vectors
        to the sphere's centre, cos_a (P,) the cone's half-angle cosine (-1 inside the sphere), cone_only (P,)
        bool (on the plane, outside the sphere: cone rays only), split (P,) bool (off the plane, outside: half
        cone, half cosine rays)); receivers that are neither take cosine rays only."""
        vec = self.centre[None, :] - pos
        dist = np.linalg.norm(vec, axis=1)
        outside = dist > self.radius
        axis = vec / np.maximum(dist, 1e-30)[:, None]
        cos_a = np.where(outside, np.sqrt(np.clip(1 - (self.radius / np.maximum(dist, 1e-30)) ** 2, 0, 1)), -1.0)
        return axis, cos_a, outside & on_plane, outside & ~on_plane

    def _directions(self, pos, nrm, keys, n_rays, on_plane):
        """Per receiver n_rays directions and weights (P, R, 3), (P, R): cone rays to the object's bounding
        sphere and/or cosine rays (see the module docstring); weight = the ray's share of the receiver's
        cosine-weighted mean (so sum weight * L(hit) is the irradiance / pi of the surfaces hit)."""
        P = pos.shape[0]
        R = int(n_rays)
        lat = sobol4(R)
        s1, s2 = _shifts(keys, self.seed)
        u = to_unit(lat[None, :, 0] ^ s1[:, None])
        w = to_unit(lat[None, :, 1] ^ s2[:, None])
        t, b = _frames(nrm)
        axis, cos_a, cone_only, split = self._cones(pos, on_plane)
        cone = cone_only | split
        # each receiver takes cosine rays (inside the sphere), cone rays (on the plane) or both (split): each set
        # is computed only for the receivers that use it (the formulas are per receiver, so the same bits)
        cphi, sphi = np.cos(2 * np.pi * w), np.sin(2 * np.pi * w)
        d = np.empty((P, R, 3))
        wt = np.full((P, R), 1.0 / R)
        cos_rows = np.flatnonzero(~cone)
        if cos_rows.size:  # cosine-distributed directions (Malley)
            uc = u[cos_rows]
            r = np.sqrt(uc)
            lz = np.sqrt(np.clip(1 - uc, 0, 1))
            d[cos_rows] = ((r * cphi[cos_rows])[..., None] * t[cos_rows, None, :]
                           + (r * sphi[cos_rows])[..., None] * b[cos_rows, None, :]
                           + lz[..., None] * nrm[cos_rows, None, :])
        if cone.any():  # cone directions (uniform in solid angle about the axis)
            ci = np.flatnonzero(cone)
            ta, ba = _frames(axis[ci])
            ct = 1 - u[ci] * (1 - cos_a[ci, None])
            st = np.sqrt(np.clip(1 - ct * ct, 0, 1))
            d_cone = ((st * cphi[ci])[..., None] * ta[:, None, :] + (st * sphi[ci])[..., None] * ba[:, None, :]
                      + ct[..., None] * axis[ci, None, :])
            omega = 2 * np.pi * (1 - cos_a[ci])
            cosn = np.einsum("prx,px->pr", d_cone, nrm[ci])
            only = cone_only[ci]
            d[ci[only]] = d_cone[only]
            wt[ci[only]] = np.maximum(cosn[only], 0) * (omega[only, None] / (np.pi * R))
            if split.any():
                # the first half of the rays: the cone (its own Sobol points 0 .. R/2 - 1), the second half:
                # cosine rays counted outside the cone (points 0 .. R - R/2 - 1, another shift); each half
                # weighted as a full estimate of its part of the hemisphere
                sp_ = ~only
                idx = ci[sp_]
                nc = R // 2
                nh = R - nc
                t3, t4 = _shifts(keys[idx], self.seed + 7919)
                uh = to_unit(lat[None, :nh, 0] ^ t3[:, None])
                vh = to_unit(lat[None, :nh, 1] ^ t4[:, None])
                rh, ph = np.sqrt(uh), 2 * np.pi * vh
                dh = ((rh * np.cos(ph))[..., None] * t[idx, None, :] + (rh * np.sin(ph))[..., None] * b[idx, None, :]
                      + np.sqrt(np.clip(1 - uh, 0, 1))[..., None] * nrm[idx, None, :])
                in_cone = np.einsum("prx,px->pr", dh, axis[idx]) > cos_a[idx, None]
                d[idx, :nc] = d_cone[sp_, :nc]
                wt[idx, :nc] = np.maximum(cosn[sp_, :nc], 0) * (omega[sp_, None] / (np.pi * nc))
                d[idx, nc:] = dh
                wt[idx, nc:] = np.where(in_cone, 0.0, 1.0 / nh)
        return d, wt

    def _rays(self, pos, nrm, keys, n_rays, on_plane):
        """The rays of :meth:`_directions` (Ray3f, weight Float; lane = receiver * n_rays + ray) computed in Dr.Jit,
        float32, from per-receiver constants (shifts, frames, cone) made in numpy: no (P, R, 3) array."""
        import drjit as dr

        mi = use_mitsuba()
        P, R = pos.shape[0], int(n_rays)
        lat = sobol4(R)
        s1, s2 = _shifts(keys, self.seed)
        t3, t4 = _shifts(keys, self.seed + 7919)
        axis, cos_a, cone_only, split = self._cones(pos, on_plane)
        kind = np.where(cone_only, 1, np.where(split, 2, 0)).astype(np.uint32)  # 0 cosine, 1 cone, 2 both
        t, b = _frames(nrm)
        ta, ba = _frames(axis)
        omega = 2 * np.pi * (1 - cos_a)
        nc = R // 2
        nh = R - nc
        # per receiver: the weight of a cone ray per unit cosine (its share: R rays, or nc in a split receiver)
        wcone = np.where(split, omega / (np.pi * max(nc, 1)), omega / (np.pi * R))

        def f3(a):
            a = np.asarray(a, np.float32)
            return mi.Vector3f(*(padded(a[:, i]) for i in range(3)))  # objcam.dr_memory

        lane = dr.arange(mi.UInt32, P * R)
        rcv = lane // dr.opaque(mi.UInt32, R)
        ray = lane - rcv * dr.opaque(mi.UInt32, R)
        g3 = lambda a: dr.gather(mi.Vector3f, a, rcv)  # noqa: E731
        g1 = lambda a, T=mi.Float: dr.gather(T, a, rcv)  # noqa: E731
        N, T, B, TA, BA, AX = (g3(f3(a)) for a in (nrm, t, b, ta, ba, axis))
        K = g1(mi.UInt32(padded(kind)), mi.UInt32)
        CA = g1(mi.Float(padded(cos_a, np.float32)))
        WC = g1(mi.Float(padded(wcone, np.float32)))
        OMC = g1(mi.Float(padded(1 - cos_a, np.float32)))
        LU, LV = mi.UInt32(padded(lat[:, 0])), mi.UInt32(padded(lat[:, 1]))
        inv24 = float(2.0**-24)

        def unit(x, shift):
            return (mi.Float((x ^ shift) >> 8) + 0.5) * inv24

        # second half of a split receiver: cosine rays of its own points 0 .. nh - 1, another shift
        second = (K == 2) & (ray >= nc)
        ri = dr.select(second, ray - nc, ray)
        u = unit(dr.gather(mi.UInt32, LU, ri), dr.select(second, g1(mi.UInt32(padded(t3)), mi.UInt32),
                                                          g1(mi.UInt32(padded(s1)), mi.UInt32)))
        w = unit(dr.gather(mi.UInt32, LV, ri), dr.select(second, g1(mi.UInt32(padded(t4)), mi.UInt32),
                                                          g1(mi.UInt32(padded(s2)), mi.UInt32)))
        sphi, cphi = dr.sincos(2 * np.pi * w)
        # cosine-distributed (Malley) about the normal
        r = dr.sqrt(u)
        d_cos = (r * cphi) * T + (r * sphi) * B + dr.safe_sqrt(1 - u) * N
        # uniform in the cone about the axis (1 - cos from the cone's 1 - cos_a, given in float64: a distant
        # receiver's cone is narrow, and 1 - ct^2 in float32 would lose its sine)
        one_m = u * OMC
        ct = 1 - one_m
        st = dr.safe_sqrt(one_m * (2 - one_m))
        d_cone = (st * cphi) * TA + (st * sphi) * BA + ct * AX
        cone = (K == 1) | ((K == 2) & ~second)
        d = dr.select(cone, d_cone, d_cos)
        w_cone = dr.maximum(dr.dot(d_cone, N), 0) * WC
        w_cos = dr.select(second, dr.select(dr.dot(d_cos, AX) > CA, 0.0, 1.0 / nh), 1.0 / R)
        wt = dr.select(cone, w_cone, w_cos)
        o = g3(f3(pos))
        return mi.Ray3f(mi.Point3f(o), d), wt

    def directions_dr(self, pos, nrm, keys, n_rays, on_plane) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_rays` as numpy arrays shaped like :meth:`_directions`' ((P, R, 3), (P, R)): for tests."""
        ray, wt = self._rays(pos, nrm, keys, n_rays, on_plane)
        P, R = pos.shape[0], int(n_rays)
        return (np.asarray(ray.d, np.float64).T.reshape(P, R, 3), np.asarray(wt, np.float64).reshape(P, R))

    def matrix(self, pos: np.ndarray, nrm: np.ndarray, weight: np.ndarray, rows: np.ndarray, n_rows: int,
               keys: np.ndarray, n_rays: int, on_plane: np.ndarray) -> sp.csr_matrix:
        """Sparse (n_rows, S_live) gather matrix of receivers: pos, nrm (P, 3) (pos already pushed off its
        surface), weight (P,) the receiver's share of its row (1 / its row's receiver count), rows (P,) its row,
        keys (P,) distinct integers (seeding its directions), n_rays rays each; the receiver albedo is NOT
        included (callers scale rows)."""
        import drjit as dr

        mi = use_mitsuba()
        t0 = time.perf_counter()
        nodes = self.nodes
        out_r, out_c, out_w = [], [], []
        split = nodes.object_split.any_split  # hits on the object are placed in its faces' parts
        per = max(1, _BATCH // max(1, n_rays))
        R = int(n_rays)
        for a in range(0, pos.shape[0], per):
            b = min(pos.shape[0], a + per)
            ray, wt = self._rays(pos[a:b], nrm[a:b], keys[a:b], R, on_plane[a:b])  # lane = receiver * R + ray
            active = wt > 0
            # ray_intersect in its two steps: the first's barycentric coordinates place a hit in its split face
            pi = self.geo.mi_scene.ray_intersect_preliminary(ray, active=active)
            si = pi.compute_surface_interaction(ray, active=active)
            valid = si.is_valid()
            shp = dr.reinterpret_array(mi.UInt32, si.shape)
            # only the front side of a surface reflects (Mitsuba's diffuse BSDF is one-sided)
            front = valid & (dr.dot(si.n, ray.d) < 0)
            dr.eval(front, shp, si.prim_index, si.p, wt, *((pi.prim_uv,) if split else ()))
            wt_np = np.asarray(wt)
            hit = np.flatnonzero(np.asarray(front, bool))  # lanes
            self.stats.rays += int(np.count_nonzero(wt_np > 0))
            sid = np.asarray(shp, np.int64)[hit]
            prim = np.asarray(si.prim_index, np.int64)[hit]
            node = np.full(sid.size, -1, np.int64)
            on_o = sid == self.geo.object_id
            sub = prim[on_o]
            if split:  # the sub-triangle the hit lies in
                uv = np.asarray(pi.prim_uv)[:, hit[on_o]]
                sub = nodes.object_split.locate_uv(sub, uv[0], uv[1])
            node[on_o] = nodes.object_face_node[sub]
            on_s = sid == self.geo.support_id
            if nodes.grid is not None:
                p = np.asarray(si.p)[:2, hit[on_s]].T.astype(np.float64)
                cell = nodes.grid.cell_of(p[:, :2])
                node[on_s] = np.where(cell >= 0, nodes.n_object + cell, -1)
            else:
                node[on_s] = nodes.n_object + nodes.support_face_node[prim[on_s]]
            ok = node >= 0
            live = np.where(ok, nodes.live[np.maximum(node, 0)], -1)
            ok &= live >= 0
            hl = hit[ok]
            hp = hl // R
            self.stats.hits += int(ok.sum())
            out_r.append(rows[a:b][hp])
            out_c.append(live[ok])
            out_w.append(wt_np[hl].astype(np.float64) * weight[a:b][hp])
        r = np.concatenate(out_r) if out_r else np.zeros(0, np.int64)
        c = np.concatenate(out_c) if out_c else np.zeros(0, np.int64)
        w = np.concatenate(out_w) if out_w else np.zeros(0)
        W = sp.coo_matrix((w, (r, c)), shape=(n_rows, nodes.count)).tocsr()
        W.sum_duplicates()
        self.stats.seconds += time.perf_counter() - t0
        return W


def _receivers(samples: PixelSamples, geo: SceneGeometry):
    """Flatten the hitting samples of a PixelSamples into receivers: (pos, normal, weight, row, key, on_object,
    on_plane, rho (P, 3))."""
    hit = samples.hit
    rows, ks = np.nonzero(hit)
    k = hit.shape[1]
    pos = samples.pos[rows, ks]
    nrm = samples.normal[rows, ks]
    weight = np.full(rows.size, 1.0 / k)  # a row is the mean over its k samples (misses add no indirect light)
    on_obj = samples.on_object[rows, ks]
    on_plane = ~on_obj & (geo.plane is not None)
    keys = samples.pixel_index[rows].astype(np.int64) * k + ks
    return pos, nrm, weight, rows, keys, on_obj, on_plane, samples.rho[rows, ks]


def gather_matrices(gather: Gather, samples: PixelSamples, rays: int, object_rays: int, channels: int,
                    salt: int) -> list[sp.csr_matrix]:
    """Per channel (1 or 3) the gather matrix of ``samples``' rows with the receivers' albedo in it: ``rays``
    per row outside the object's bounding sphere, ``object_rays`` for rows inside it (spread over a row's
    samples)."""
    pos, nrm, weight, rows, keys, on_obj, on_plane, rho = _receivers(samples, gather.geo)
    k = samples.hit.shape[1]
    keys = keys * 2 + salt
    # rows with a receiver inside the object's bounding sphere sample the whole hemisphere, where most of the
    # indirect light is (the object lit by the support, the support beneath the object)
    inside = np.linalg.norm(pos - gather.centre, axis=1) <= gather.radius
    row_obj = np.zeros(samples.hit.shape[0], bool)
    row_obj[rows[inside | on_obj]] = True
    groups = [(sel, max(1, -(-int(n) // k))) for sel, n in ((row_obj[rows], object_rays), (~row_obj[rows], rays))]
    ch = [rho.mean(axis=1)] if channels == 1 else [rho[:, c] for c in range(3)]
    out = []
    for r in ch:
        # the same rays for every channel (same keys); only the albedo weights differ
        W = None
        for sel, n in groups:
            if sel.any():
                Wg = gather.matrix(pos[sel], nrm[sel], (weight * r)[sel], rows[sel], samples.hit.shape[0],
                                   keys[sel], n, on_plane[sel])
                W = Wg if W is None else W + Wg
        out.append((W if W is not None else sp.csr_matrix((samples.hit.shape[0], gather.nodes.count)))
                   .astype(np.float32))
    return out


class GatherIndirect:
    """Indirect-light columns of A for the pixels of ``pixels`` by the node gather (module docstring)."""

    def __init__(self, geo: SceneGeometry, pixels: SampleParts | PixelSamples, texel_index: np.ndarray,
                 env_height: int, channels: int, settings: GatherSettings | None = None, batch_rays: int = 1 << 24,
                 keep_parts: bool = False):
        """keep_parts: keep what :meth:`bounce_parts` returns (the nodes' direct light of every column, ~S x N
        floats, and the plane cell under each pixel), for a support whose bounce albedo is a guess."""
        from objcam.transport.direct import DirectModel

        s = settings or GatherSettings()
        self.s, self.channels = s, int(channels)
        self.texel_index = np.asarray(texel_index, np.int64)
        t0 = time.perf_counter()
        self.nodes = surface_nodes(geo, s)
        self.gather = Gather(geo, self.nodes, s.seed)
        self.bounces = max(0, int(s.max_depth) - 3) if s.max_depth >= 0 else 8
        parts = pixels if isinstance(pixels, SampleParts) else SampleParts.single(pixels)
        m = parts.pixel_index.size
        self.W_pix = None
        for rows, ps in parts.parts:
            # a part's rows scattered into the M kept pixels
            place = sp.csr_matrix((np.ones(rows.size, np.float32), (rows, np.arange(rows.size))),
                                  shape=(m, rows.size))
            Ws = [(place @ W).tocsr() for W in gather_matrices(self.gather, ps, s.rays, s.object_rays,
                                                               self.channels, salt=0)]
            self.W_pix = Ws if self.W_pix is None else [a + b for a, b in zip(self.W_pix, Ws)]
        self.W_node = gather_matrices(self.gather, self.nodes.samples, s.node_rays, s.node_rays, self.channels,
                                      salt=1) if self.bounces else None
        self.dm = DirectModel(geo, self.nodes.samples, env_height, self.channels, rays=s.node_shadow_rays,
                              seed=s.seed + 1, batch_rays=batch_rays, refine=False)
        # the plane cell (live node row) under each kept pixel, -1 where it sees the object or no plane: what a
        # later albedo estimate of those pixels says about the cells' bounce albedo (bounce_parts)
        self.keep_parts = bool(keep_parts)
        self.pixel_node = np.full(m, -1, np.int64)
        if self.keep_parts and self.nodes.grid is not None:
            for rows, ps in parts.parts:
                on_plane = ps.hit & ~ps.on_object
                first = np.argmax(on_plane, axis=1)
                ok = on_plane[np.arange(rows.size), first]
                xy = ps.pos[np.arange(rows.size), first, :2]
                cell = self.nodes.grid.cell_of(xy[ok])
                node = np.where(cell >= 0, self.nodes.live[self.nodes.n_object + np.maximum(cell, 0)], -1)
                self.pixel_node[rows[ok]] = node
        # the object node under each kept pixel that sees the object (-1 elsewhere): the object's own albedo estimate
        # there says what it reflects onto the support (a bounce refit of an object of unknown albedo)
        self.pixel_object_node = np.full(m, -1, np.int64)
        n_obj_live = int((self.nodes.live[: self.nodes.n_object] >= 0).sum())  # object nodes' rows come first
        if self.keep_parts and n_obj_live:
            from scipy.spatial import cKDTree

            hit = self.nodes.samples.hit[:n_obj_live]
            node_of = np.broadcast_to(np.arange(n_obj_live)[:, None], hit.shape)[hit]
            tree = cKDTree(self.nodes.samples.pos[:n_obj_live][hit])
            for rows, ps in parts.parts:
                first = np.argmax(ps.hit, axis=1)
                pick = np.arange(rows.size)
                ok = ps.hit[pick, first] & ps.on_object[pick, first]
                if ok.any():
                    _, j = tree.query(ps.pos[pick, first][ok])  # the nearest of the object nodes' points
                    self.pixel_object_node[rows[ok]] = node_of[j]
        self.E = None  # (C, S, N) float32: the nodes' direct light of every column, kept for bounce_parts
        self._blocks = None  # one channel: the gather matrices' row blocks, one per thread (columns)
        self.seconds_setup = time.perf_counter() - t0
        self.seconds_columns = 0.0

    def columns(self, a: int, b: int, channels: int | None = None) -> np.ndarray:
        """(C, M, b - a) float32 indirect light of kept texels a .. b - 1 (positions into texel_index)."""
        t0 = time.perf_counter()
        tex = self.texel_index[a:b]
        E = self.dm.columns(tex)  # (C, S, B): direct light leaving each node
        if self.keep_parts:
            if self.E is None:
                self.E = np.zeros((self.channels, E.shape[1], self.texel_index.size), np.float32)
            self.E[:, :, a:b] = E
        # the channels' sparse products are independent (scipy releases the GIL): one per core; one channel (a
        # grey albedo): its products split by rows instead
        if self.channels == 1:
            if self._blocks is None:
                self._blocks = {"pix": row_blocks(self.W_pix[0]),
                                "node": row_blocks(self.W_node[0]) if self.bounces else None}
            bl = self._blocks
            mul = (lambda W, X: _blocks_matmul(bl["node"], X)) if self.bounces else None
            out = [_blocks_matmul(bl["pix"], _propagate(E[0], self.W_node[0] if self.bounces else None, self.bounces,
                                                        mul=mul))]
        else:
            out = parallel_map(lambda c: self.W_pix[c] @ _propagate(E[c], self.W_node[c] if self.bounces else None,
                                                                    self.bounces), range(self.channels))
        self.seconds_columns += time.perf_counter() - t0
        return np.stack(out).astype(np.float32)

    def bounce_parts(self) -> dict[str, np.ndarray]:
        """What :func:`bounce_delta` needs to redo the indirect columns for new plane-cell albedos (after every
        column was computed): the gather matrices and the nodes' direct light, with the albedos they hold."""
        if not self.keep_parts or self.E is None:
            raise RuntimeError("bounce_parts: build with keep_parts=True and compute the columns first")
        out: dict[str, np.ndarray] = {"E": self.E, "node_rho": self.nodes.rho.astype(np.float32),
                                      "node_unknown": self.nodes.samples.unknown.any(axis=1),
                                      "pixel_node": self.pixel_node, "pixel_object_node": self.pixel_object_node,
                                      "node_object": self.nodes.samples.on_object.any(axis=1),
                                      "bounces": np.array(self.bounces)}
        for c in range(self.channels):
            for name, W in (("W_pix", self.W_pix[c]), ("W_node", self.W_node[c] if self.W_node else None)):
                if W is None:
                    continue
                W = W.tocsr()
                out.update({f"{name}{c}_data": W.data, f"{name}{c}_indices": W.indices,
                            f"{name}{c}_indptr": W.indptr, f"{name}{c}_shape": np.array(W.shape)})
        return out

    def metrics(self) -> dict:
        n = self.nodes
        return {"gather_nodes": n.count, "gather_nodes_object": int((n.live[:n.n_object] >= 0).sum()),
                "gather_rays": self.gather.stats.rays, "gather_hits": self.gather.stats.hits,
                "gather_nnz_pixels": int(self.W_pix[0].nnz),
                "gather_nnz_nodes": int(self.W_node[0].nnz) if self.W_node else 0,
                "gather_bounces": self.bounces + 1, "gather_setup_seconds": round(self.seconds_setup, 3),
                "gather_columns_seconds": round(self.seconds_columns, 3),
                "gather_node_direct_rays": self.dm.stats.rays_traced}


def _csr(parts: dict, name: str) -> sp.csr_matrix | None:
    if f"{name}_data" not in parts:
        return None
    return sp.csr_matrix((parts[f"{name}_data"], parts[f"{name}_indices"], parts[f"{name}_indptr"]),
                         shape=tuple(int(v) for v in parts[f"{name}_shape"]))


def row_blocks(W: sp.csr_matrix) -> list[sp.csr_matrix]:
    """W's rows cut into one block of about equal nonzeros per thread of Dr.Jit's pool (every core in-process; a
    Dask worker's share of its host: objcam.transport.shards); [W] alone when small or on one thread."""
    import drjit as dr

    n = min(cores(), max(1, int(dr.thread_count())))
    if n <= 1 or W.nnz < (1 << 15) or W.shape[0] < 2 * n:
        return [W]
    cuts = np.unique(np.searchsorted(W.indptr, np.linspace(0, W.nnz, n + 1), side="left").clip(0, W.shape[0]))
    cuts[0], cuts[-1] = 0, W.shape[0]
    return [W[a:b] for a, b in zip(cuts[:-1], cuts[1:])]


def _blocks_matmul(blocks: list[sp.csr_matrix], X: np.ndarray) -> np.ndarray:
    """W @ X (dense X) for W given as :func:`row_blocks`, the blocks on threads: scipy's product releases the
    GIL, and a row's sum is computed the same way whichever block holds it, so the result is the bits of W @ X."""
    if len(blocks) == 1:
        return blocks[0] @ X
    return np.concatenate(parallel_map(lambda B: B @ X, blocks), axis=0)


def _propagate(E: np.ndarray, W_node: sp.csr_matrix | None, bounces: int, scale: np.ndarray | None = None,
               mul=None) -> np.ndarray:
    """(S, B) light leaving the nodes, summed over their direct light E (S, B) and ``bounces`` node-to-node
    gathers; ``scale`` (S,) multiplies every node's albedo (E and each gather scale by row: the node reflects).
    ``mul(W_node, L)``: the sparse-dense product (default ``W_node @ L``)."""
    s = None if scale is None else scale[:, None]
    L = E if s is None else E * s
    acc = L.copy()
    for _ in range(bounces):
        WL = W_node @ L if mul is None else mul(W_node, L)
        L = WL if s is None else s * WL
        acc += L
    return acc


def _node_light(parts: dict, scale: np.ndarray, channel: int, dtype=np.float64) -> np.ndarray:
    """(S, N) :func:`_propagate` of the stored parts of one channel, with node albedos scaled by ``scale``."""
    return _propagate(parts["E"][channel].astype(dtype), _csr(parts, f"W_node{channel}"), int(parts["bounces"]),
                      np.asarray(scale, dtype=dtype))


def bounce_indirect(parts: dict, scale: np.ndarray, channel: int = 0) -> np.ndarray:
    """(M, N) float64 indirect columns of :class:`GatherIndirect` with every node's albedo multiplied by
    ``scale`` (S,); the pixels' gather does not scale (the receiving pixel's own albedo is kept as it was, 1 where
    unknown: A = diag(rho) A')."""
    return np.asarray(_csr(parts, f"W_pix{channel}") @ _node_light(parts, scale, channel))


def bounce_delta(parts: dict, rho: np.ndarray, rows: np.ndarray, rho_min: float = 1e-3
                 ) -> tuple[np.ndarray | None, dict]:
    """The change of A' (rows ``rows``, this group's N texels) when the surface nodes of unknown albedo reflect
    with the mean of the albedo estimated at the pixels that see them (the support's plane cells, and the object's
    nodes when its albedo is unknown), instead of the albedo the transport assumed; the free nodes no pixel sees
    take the count-weighted mean of the seen free nodes of the same surface (the object's, or the support's).

    rho: (len(rows), C') the estimate at ``rows`` (grey: mean over channels). Returns (dA (len(rows), N) float32
    per channel-mean, or None when no node is seen) and a summary dict."""
    old = parts["node_rho"].mean(axis=1).astype(np.float64)
    n_nodes = old.size
    free = parts["node_unknown"] & (old > 0)
    grey = np.asarray(rho, np.float64).reshape(rows.size, -1).mean(axis=1)
    # the node each pixel sees: a plane cell, else an object node
    pn = np.where(parts["pixel_node"][rows] >= 0, parts["pixel_node"][rows], parts["pixel_object_node"][rows])
    is_object = parts["node_object"]
    seen = pn >= 0
    cnt = np.bincount(pn[seen], minlength=n_nodes)
    tot = np.bincount(pn[seen], weights=grey[seen], minlength=n_nodes)
    upd = (cnt > 0) & free
    if not upd.any():
        return None, {"cells_updated": 0}
    new = old.copy()
    new[upd] = np.clip(tot[upd] / cnt[upd], rho_min, 1.0)
    # free nodes no pixel sees (support cells beside and behind the object or outside the view, the object's far
    # side) light the scene too: left at the transport's guessed albedo they bias every pixel's indirect light, so
    # they take the seen nodes' mean estimate over the same surface (count-weighted: the mean albedo over the pixels
    # that see it)
    unseen = (cnt == 0) & free
    fills = {}
    for name, kind in (("support", ~is_object), ("object", is_object)):
        sk, uk = upd & kind, unseen & kind
        if sk.any() and uk.any():
            fills[name] = float(np.clip(tot[sk].sum() / cnt[sk].sum(), rho_min, 1.0))
            new[uk] = fills[name]
        else:
            unseen &= ~kind  # nothing of that surface seen: its unseen nodes keep the guess
    changed = upd | unseen
    scale = np.ones(n_nodes)
    scale[changed] = new[changed] / old[changed]
    C = parts["E"].shape[0]
    # one pass of the pixels' gather over the difference of the nodes' light, in float32 (the change is a few % of
    # the indirect part, itself a few % of A), for the wanted rows only
    dA = np.zeros((rows.size, parts["E"].shape[2]), np.float32)
    for c in range(C):
        # the two propagations are independent sparse products (scipy releases the GIL): one per core
        lit, base = parallel_map(lambda sc, c=c: _node_light(parts, sc, c, np.float32), [scale, np.ones(n_nodes)])
        dA += np.asarray(_csr(parts, f"W_pix{c}")[rows] @ (lit - base)) / C
    sup, obj = upd & ~is_object, upd & is_object
    info = {"cells_updated": int(sup.sum()), "object_nodes_updated": int(obj.sum()),
            "cells_unseen_filled": int((unseen & ~is_object).sum()),
            "object_nodes_unseen_filled": int((unseen & is_object).sum())}
    if sup.any():
        info.update(cell_albedo_before=float(np.mean(old[sup])), cell_albedo_after=float(np.mean(new[sup])))
    if obj.any():
        info.update(object_albedo_before=float(np.mean(old[obj])), object_albedo_after=float(np.mean(new[obj])))
    if "support" in fills:
        info["unseen_cell_albedo"] = fills["support"]
    if "object" in fills:
        info["unseen_object_albedo"] = fills["object"]
    return dA, info
