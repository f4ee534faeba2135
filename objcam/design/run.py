"""``objcam design``: build, score and draw every occluder on the shared setup, and write the OUT folder.

    OUT/
      design.json               params, setup (camera, ridge weight), per occluder its numbers and timings
      comparison.png            side by side: view | uncertainty | leverage per occluder, shared colour scales
      index.html                the figure and the table (self-contained)
      <occluder>/uncertainty.exr|.png   (H, 2H) per texel; the ridge bound where an upper texel lights nothing,
                                        0 (EXR) / grey (PNG) below the horizon
      <occluder>/leverage.exr|.png      (H', W') per pixel; 0 (EXR) / grey (PNG) where no surface is seen
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from objcam.design.params import DesignParams


@dataclass
class DesignResult:
    """What :func:`run_design` wrote: the ``design.json`` content and the scores by occluder name."""

    results: dict
    scores: dict


def run_design(out: str | Path, params: DesignParams | None = None,
               log: Callable[[str], None] | None = None) -> DesignResult:
    """Compare the occluders of ``params`` and write ``out`` (created; existing files in it are replaced)."""
    from objcam.design.figures import comparison_figure, shared_limits, write_object_pngs
    from objcam.design.occluders import occluders
    from objcam.design.page import write_page
    from objcam.design.scene import build_transport, design_camera, reference_scale
    from objcam.design.scoring import score
    from objcam.envmap import write_latlong
    from objcam.image_io import atomic_write_text, write_exr

    p = params or DesignParams()
    say = log or (lambda _msg: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    objs = occluders(p.objects, p.meshes, p.size, p.mask_height, p.mask_cells, p.mask_open, p.mask_seed)
    if not objs:
        from objcam.errors import InputError

        raise InputError("nothing to compare", None, "name built-in occluders with --objects or pass --mesh FILE")
    camera = design_camera(p)
    lr = p.lr * reference_scale(p, camera)
    scores, entries = {}, {}
    for o in objs:
        t0 = time.perf_counter()
        tr, build = build_transport(o.mesh, p, camera)
        t1 = time.perf_counter()
        sc = score(tr, lr, threshold=p.threshold, rank_tol=p.rank_tol, zenith_deg=p.zenith_deg,
                   horizon_deg=p.horizon_deg)
        t2 = time.perf_counter()
        scores[o.name] = sc
        entries[o.name] = {"kind": o.kind, "source": o.source, "faces": int(len(o.mesh.faces)),
                           "numbers": sc.numbers,
                           "seconds": {"transport": round(t1 - t0, 3), "analysis": round(t2 - t1, 3)},
                           "transport": {k: build.get(k) for k in ("pixels_kept", "texels_kept", "rays_traced",
                                                                     "pairs_traced")}}
        say(f"{o.name}: A {sc.numbers['pixels']} x {sc.numbers['texels']} in {t1 - t0:.1f} s, scored in "
            f"{t2 - t1:.1f} s")
    # every map on one colour scale per kind
    unc_lim = shared_limits([s.uncertainty for s in scores.values()])
    lev_lim = shared_limits([s.leverage for s in scores.values()])
    for name, sc in scores.items():
        write_latlong(out / name / "uncertainty.exr", np.nan_to_num(sc.uncertainty).astype(np.float32))
        write_exr(out / name / "leverage.exr", np.nan_to_num(sc.leverage).astype(np.float32))
        write_object_pngs(out / name, name, sc, unc_lim, lev_lim)
    comparison_figure(out / "comparison.png", list(scores), list(scores.values()), unc_lim, lev_lim,
                      p.horizon_deg, p.zenith_deg)
    results = {
        "format": 1,
        "params": p.model_dump(mode="json"),
        "setup": {"camera": camera.model_dump(), "camera_distance_m": p.distance * p.size,
                  "lr_absolute": lr, "uncertainty_bound": float(1.0 / np.sqrt(lr)),
                  "resolved_below": float(p.threshold / np.sqrt(lr)),
                  "units": "uncertainty: envmap radiance per unit pixel noise (standard deviations)"},
        "objects": entries,
    }
    atomic_write_text(out / "design.json", json.dumps(results, indent=2))
    write_page(out / "index.html", results, out / "comparison.png")
    return DesignResult(results, scores)
