"""From a capture's targets and transport matrices to the joint problems of :func:`objcam.solvers.solve_joint`.

Two facts of the capture decide the coupling (data_layout.md, ``solve/``):

* camera: targets whose transport stage put them in one group (identical camera, so one A) share the albedo rho
  of that camera's pixels;
* illumination: targets with the same ``illumination`` name in capture.toml (default: the target's own name) show
  the same envmap x, so the cameras that see it stack their rows into one system for that x.

The bipartite graph cameras -- illuminations splits into connected components; each component is one joint problem
with P cameras and L illuminations. :func:`solve_joint` needs every camera of a component to see every one of its
illuminations (Y is (M_p, L, C) per camera); a component with a hole is refused (one line naming the missing
pair). The texels of a component are the union of its cameras' kept texels; a camera's A' gets zero columns for
texels it does not see. A camera's rows are the pixels usable in every one of its targets.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class CameraData:
    """One camera (transport group) of a component: its transport, its targets by illumination, and its rows.

    transport: objcam.transport.Transport; targets: {illumination: target name}; use: (M,) bool rows of A used
    (usable in every target of this camera); Y: {illumination: (M, 3) float64 pooled pixel values at A's rows};
    pooled: {target: (H', W', 3) pooled target}; pooled_ok: {target: (H', W') bool}.
    """

    key: str
    transport: object
    targets: dict[str, str] = field(default_factory=dict)
    use: np.ndarray | None = None
    Y: dict[str, np.ndarray] = field(default_factory=dict)
    pooled: dict[str, np.ndarray] = field(default_factory=dict)
    pooled_ok: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Component:
    """One joint problem: cameras (keys in order), illuminations (names in order), texel union (N,)."""

    cameras: list[str]
    illuminations: list[str]
    texel_index: np.ndarray


def components(pairs: list[tuple[str, str, str]]) -> list[Component]:
    """Connected components of (camera, illumination, target) triples; texel_index is filled in later.

    Raises ValueError naming the first (camera, illumination) pair a component lacks, or a duplicate pair.
    """
    parent: dict[tuple[str, str], tuple[str, str]] = {}

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    seen: dict[tuple[str, str], str] = {}
    for cam, ill, tgt in pairs:
        if (cam, ill) in seen:
            raise ValueError(f"targets {seen[(cam, ill)]!r} and {tgt!r} have the same camera and the same "
                             f"illumination {ill!r}: give them different illumination names")
        seen[(cam, ill)] = tgt
        for node in (("c", cam), ("i", ill)):
            parent.setdefault(node, node)
        ra, rb = find(("c", cam)), find(("i", ill))
        if ra != rb:
            parent[ra] = rb
    groups: dict[tuple[str, str], tuple[list[str], list[str]]] = {}
    for cam, ill, _ in pairs:  # first-seen order, so the output follows the capture's target order
        cams, ills = groups.setdefault(find(("c", cam)), ([], []))
        if cam not in cams:
            cams.append(cam)
        if ill not in ills:
            ills.append(ill)
    out = []
    for cams, ills in groups.values():
        for c in cams:
            for i in ills:
                if (c, i) not in seen:
                    some = next(t for (cc, ii), t in seen.items() if cc == c)
                    raise ValueError(f"the camera of target {some!r} has no target under illumination {i!r}, "
                                     "which another camera of the same envmap sees: a joint solve needs every "
                                     "camera of an illumination group to see all its illuminations")
        out.append(Component(cams, ills, np.zeros(0, np.int64)))
    return out


def grey_rho_free(transport, rows: np.ndarray, texel_union: np.ndarray) -> np.ndarray:
    """A' (M_used, N_union) float32: the transport with the albedo divided out, one grey matrix per camera.

    With C = 3 (coloured known albedo somewhere) the per-channel A'_c agree for direct light and differ only in
    the interreflections' colour; their mean is used. Columns of texels this camera does not keep are 0.
    """
    Ap = transport.rho_free(rows)  # (C, M_used, N_own)
    Ap = Ap[0] if Ap.shape[0] == 1 else Ap.mean(axis=0)
    own = np.asarray(transport.texel_index)
    if own.size == texel_union.size and np.array_equal(own, texel_union):
        return np.ascontiguousarray(Ap, dtype=np.float32)
    out = np.zeros((Ap.shape[0], texel_union.size), np.float32)
    out[:, np.searchsorted(texel_union, own)] = Ap
    return out
