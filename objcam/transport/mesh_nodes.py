"""The gather's nodes on a mesh: which faces, or which parts of faces, share one radiance.

A node carries one value per texel, its points' average (objcam.transport.gather). One node per face is right for
a scanned mesh's small, even faces, but a CAD-like mesh has long ones: a mug's inner wall is one 74-mm triangle
from the floor to the rim, dim at its foot and bright at its rim, and with its average radiance the floor saw a
wall ~2x too bright (the hard suite's held-out mug seen from 75 deg: floor pixels 1.4-2.5x the path-traced photo,
within 2% with bounded nodes; bench/results.md, issue 22 session 45). So a face longer than ``NODE_SPAN`` x the
object's radius is split into a regular grid of sub-triangles, and those are grouped into cells of that side (by
normal direction as well, so a node never mixes opposite sides): the nodes span at most about ``NODE_SPAN`` x the
radius whatever the mesh's faces, and a mesh without such faces keeps one node per face. A gather ray's hit is
placed in its sub-triangle by the barycentric coordinates Mitsuba's intersection gives (``locate_uv``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the longest a face may be, as a fraction of the object's radius (half its bounding box's diagonal), before it
#: is split for the gather, and the side of the cells its parts are grouped in: 8 cm objects -> ~1.8 mm, about
#: the faces of the bundled 8,000-face bunny. Nodes then number ~5,000-11,000 whatever the mesh (bunny 7,342 for
#: its 8,000 faces, the frame's 120 boxes' faces 6,194, the mug 10,788). Measured on the frame (gathered indirect
#: light of its pixels against Mitsuba's path tracer, 16 texels 0-45 deg up): median column error 0.20 with one
#: node per face, 0.24 / 0.16 / 0.15 / 0.10 at spans 0.2 / 0.1 / 0.05 / 0.03, the column sums 0.53-1.18 of the path
#: tracer's with one node per face, 0.97-1.01 at 0.03 (bench/results.md, issue 22 session 45)
NODE_SPAN = 0.03
#: at most this many sub-triangles (their float64 corners are 72 bytes each): beyond, the span grows to fit
MAX_SUBTRIANGLES = 2_000_000


def longest_edges(tri: np.ndarray) -> np.ndarray:
    """(F,) the longest edge of each face (F, 3, 3)."""
    return np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)


@dataclass
class FaceSplit:
    """The faces (F, 3, 3) of a mesh split into sub-triangles: face f into ``n[f]``^2 by a regular grid of its
    barycentric coordinates (n = 1: the face itself). ``tri`` (T, 3, 3) the sub-triangles (wound as their face),
    ``parent`` (T,) their face; a point of face f at barycentric (s, t) (weights of its vertices 1 and 2) lies in
    sub-triangle ``slots[offset[f] + 2 (i n + j) + upper]`` (-1 marks unused slots)."""

    tri: np.ndarray
    parent: np.ndarray
    n: np.ndarray
    offset: np.ndarray
    slots: np.ndarray
    faces: np.ndarray  # (F, 3, 3) the faces themselves

    @property
    def any_split(self) -> bool:
        return bool((self.n > 1).any())

    @classmethod
    def of(cls, tri: np.ndarray, max_edge: float, longest: np.ndarray | None = None) -> "FaceSplit":
        """Split every face (F, 3, 3) whose longest edge exceeds ``max_edge`` into n^2 sub-triangles, n = ceil(its
        longest edge / max_edge), so that each sub-triangle's edges are at most ``max_edge``. ``longest``: the
        faces' longest edges (F,), when the caller has them (:func:`longest_edges`)."""
        tri = np.asarray(tri, np.float64)
        longest = longest_edges(tri) if longest is None else longest
        n = np.maximum(1, np.ceil(longest / max_edge - 1e-9)).astype(np.int64) if max_edge > 0 else \
            np.ones(len(tri), np.int64)
        offset = np.concatenate([[0], np.cumsum(2 * n * n)])
        slots = np.full(int(offset[-1]), -1, np.int64)
        subs, parents = [], []
        count = 0
        for m in np.unique(n):
            faces = np.flatnonzero(n == m)
            i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
            lower = (i + j <= m - 1).ravel()
            upper = (i + j <= m - 2).ravel()
            i, j = i.ravel(), j.ravel()
            # (s, t) of each sub-triangle's corners, lower ones then upper ones; slot 2 (i m + j) + upper
            st = np.concatenate([np.stack([[i, j], [i + 1, j], [i, j + 1]], 0)[:, :, lower],
                                 np.stack([[i + 1, j], [i + 1, j + 1], [i, j + 1]], 0)[:, :, upper]], axis=2) / m
            local = np.concatenate([2 * (i * m + j)[lower], 2 * (i * m + j)[upper] + 1])
            k = local.size
            a, e1, e2 = tri[faces, 0], tri[faces, 1] - tri[faces, 0], tri[faces, 2] - tri[faces, 0]
            # (faces, k, 3 corners, 3): corner = a + s e1 + t e2 (a face not split: itself, to the bit)
            sc, tc = st[:, 0].T[None, :, :, None], st[:, 1].T[None, :, :, None]  # (1, k, 3 corners, 1)
            sub = tri[faces][:, None] if m == 1 else a[:, None, None] + sc * e1[:, None, None] + tc * e2[:, None, None]
            subs.append(sub.reshape(-1, 3, 3))
            parents.append(np.repeat(faces, k))
            slots[(offset[faces][:, None] + local[None, :]).ravel()] = count + np.arange(faces.size * k)
            count += faces.size * k
        return cls(np.concatenate(subs), np.concatenate(parents), n, offset, slots, tri)

    def locate(self, face: np.ndarray, p: np.ndarray) -> np.ndarray:
        """(H,) the sub-triangle holding each point ``p`` (H, 3) that lies on face ``face`` (H,)."""
        face = np.asarray(face, np.int64)
        t = self.faces[face]
        e1, e2, d = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], np.asarray(p, np.float64) - t[:, 0]
        d00, d01, d11 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
        d20, d21 = (d * e1).sum(1), (d * e2).sum(1)
        den = np.maximum(d00 * d11 - d01 * d01, 1e-300)
        return self.locate_uv(face, (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den)

    def locate_uv(self, face: np.ndarray, b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
        """(H,) the sub-triangle holding the points of faces ``face`` (H,) at barycentric coordinates ``b1``, ``b2``
        (H,) (the weights of the face's vertices 1 and 2: Mitsuba's ``PreliminaryIntersection.prim_uv``)."""
        face = np.asarray(face, np.int64)
        n = self.n[face]
        a, c = np.asarray(b1, np.float64) * n, np.asarray(b2, np.float64) * n
        i = np.clip(np.floor(a), 0, n - 1).astype(np.int64)
        j = np.clip(np.floor(c), 0, n - 1 - i).astype(np.int64)
        up = ((a - i) + (c - j) > 1.0) & (i + j <= n - 2)
        return self.slots[self.offset[face] + 2 * (i * n + j) + up]


def cells(tri: np.ndarray, normals: np.ndarray, side: float) -> np.ndarray:
    """(T,) a group id (0..) for each triangle (T, 3, 3): the cubic cell of side ``side`` holding its centroid and
    the axis its normal (T, 3) is closest to, with its sign (6 buckets, so a group never mixes opposite sides)."""
    c = tri.mean(axis=1)
    cell = np.floor((c - c.min(axis=0)) / side).astype(np.int64)
    ax = np.argmax(np.abs(normals), axis=1)
    bucket = 2 * ax + (normals[np.arange(len(normals)), ax] < 0)
    _, group = np.unique(np.concatenate([cell, bucket[:, None]], axis=1), axis=0, return_inverse=True)
    return group.ravel()


def face_clusters(tri: np.ndarray, normals: np.ndarray, max_nodes: int) -> tuple[np.ndarray, int]:
    """(F,) node of each face and the node count: one node per face up to ``max_nodes`` faces; beyond, faces are
    grouped by :func:`cells` whose side follows from the surface area (so about max_nodes / 2 are occupied)."""
    f = tri.shape[0]
    if f <= max_nodes:
        return np.arange(f), f
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    node = cells(tri, normals, np.sqrt(area.sum() / max(1, max_nodes // 2)))
    return node, int(node.max()) + 1


def mesh_nodes(tri: np.ndarray, normals: np.ndarray, max_nodes: int, span: float | None = None
               ) -> tuple[FaceSplit, np.ndarray, int]:
    """(the faces' split, (T,) node of each sub-triangle, node count) for a mesh's faces (F, 3, 3) with normals
    (F, 3): faces longer than ``span`` x the mesh's radius split (:class:`FaceSplit`); up to ``max_nodes`` faces,
    each unsplit face its own node and the split faces' sub-triangles grouped by :func:`cells` of that length;
    beyond, every sub-triangle by :func:`face_clusters`' cells. ``span``: :data:`NODE_SPAN` by default."""
    v = tri.reshape(-1, 3)
    h = (NODE_SPAN if span is None else span) * 0.5 * float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    longest = longest_edges(tri)
    while h > 0 and float((np.ceil(longest / h) ** 2).sum()) > MAX_SUBTRIANGLES:
        h *= 1.25
    split = FaceSplit.of(tri, h, longest)
    sub_n = normals[split.parent]
    if tri.shape[0] > max_nodes:
        node, count = face_clusters(split.tri, sub_n, max_nodes)
        return split, node, count
    whole = split.n[split.parent] == 1
    node = np.empty(split.parent.size, np.int64)
    node[whole] = np.arange(int(whole.sum()))
    if not whole.all():
        node[~whole] = int(whole.sum()) + cells(split.tri[~whole], sub_n[~whole], h)
    return split, node, int(node.max()) + 1
