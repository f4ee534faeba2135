"""The scale at which a scale-ambiguous solve's albedo is exported, so that its light bounces as the solve's A said.

With every albedo unknown and no pixel of known albedo, the joint solve finds the envmap x and the albedo rho only
up to one factor c (``c rho`` and ``x / c`` fit the photos equally: solve.json ``scale_ambiguous``), and its
regularisers pick c. The direct light of a pixel, ``rho_p (A'_p x)``, does not depend on c; the interreflections
do: A' holds the light the support (and the object) reflect onto other surfaces, which the transport's gather
computed with the surfaces at the texture stage's albedo (``bounce.npz`` ``node_rho``), and which a bounce refit
(objcam.solvers.plan.bounce.refit_bounce) redoes with the estimate rescaled so that its mean over the support
pixels stays at that guess. A path tracer given the solve's albedo as it is reflects ``c`` times that light
instead (measured on tests/test_full_run.py's photographed capture: c = 0.22, the object 18% too dark, 3.1% of the
prediction over the image).

So the exported albedo is ``k rho`` and the exported envmap ``x / k`` with ``k`` = (mean of the transport's bounce
albedo under the solve's support pixels) / (mean of the solve's albedo at those pixels), both grey: the refit's own
rule. The prediction is unchanged (one factor per target, the same for every channel) and the exported surfaces
reflect, on average over the support, the albedo A' assumed. What no single scale can reconcile (the object's
nodes reflect at the texture stage's albedo in A', while the solve's estimate of the object is another multiple
of it) stays: that is the solve's model, not the export's (bench/results.md, issue 23).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class BounceScale:
    """``k`` the exported albedo's factor (envmap divided by it); ``record`` for export.json (rule and means)."""

    k: float
    record: dict


def bounce_scale(transport, solve_dir: Path) -> BounceScale:
    """:class:`BounceScale` of one target: ``transport`` its objcam.transport Transport (A not needed),
    ``solve_dir`` its ``solve/<target>`` folder. k = 1 when the scale is not ambiguous (the albedo is absolute),
    when A models no interreflections from surfaces of unknown albedo (a direct A: the render does not depend on
    k), or when no estimated support pixel lies over a cell of the gather."""
    from PIL import Image

    from objcam.image_io import read_exr

    try:
        info = json.loads((Path(solve_dir) / "solve.json").read_text())
    except (OSError, ValueError):
        info = {}
    if info.get("albedo") != "unknown" or not info.get("scale_ambiguous"):
        return BounceScale(1.0, {"albedo_scale": 1.0, "albedo_scale_rule": "the solve's scale is absolute"})
    if not transport.has_bounce_parts:
        return BounceScale(1.0, {"albedo_scale": 1.0, "albedo_scale_rule": "A has no interreflection parts: the "
                                 "render of a direct A does not depend on the albedo's scale"})
    from objcam.transport.storage import BOUNCE

    with np.load(transport.folder / BOUNCE) as z:  # two small members, not the gather's matrices
        node_rho, node = np.asarray(z["node_rho"]), np.asarray(z["pixel_node"])
    files = [Path(solve_dir) / "albedo.exr", Path(solve_dir) / "albedo_mask.png"]
    if not all(f.is_file() for f in files):
        return BounceScale(1.0, {"albedo_scale": 1.0, "albedo_scale_rule": "the solve wrote no albedo"})
    alb = read_exr(files[0])[..., :3].astype(np.float64)
    mask = np.asarray(Image.open(files[1]))
    mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
    if alb.shape[:2] != tuple(transport.image_shape) or mask.shape != alb.shape[:2]:
        return BounceScale(1.0, {"albedo_scale": 1.0, "albedo_scale_rule": "the albedo is not at A's pooled size"})
    pix = np.asarray(transport.pixel_index)
    rho = alb.reshape(-1, 3)[pix].mean(axis=1)
    on = mask.reshape(-1)[pix] & (node >= 0) & np.asarray(transport.unknown_albedo, bool) & (rho > 0)
    if not on.any():
        return BounceScale(1.0, {"albedo_scale": 1.0, "albedo_scale_rule": "no estimated pixel over a support cell"})
    guess = float(np.mean(node_rho[node[on]].mean(axis=1)))
    est = float(np.mean(rho[on]))
    k = guess / est
    return BounceScale(k, {"albedo_scale": k, "albedo_scale_rule": "mean bounce albedo A' assumed over the solve's "
                           "support pixels / the solve's mean albedo there (the exported envmap is the solve's "
                           "divided by it)", "bounce_albedo_mean": guess, "solve_albedo_mean": est,
                           "pixels": int(on.sum())})
