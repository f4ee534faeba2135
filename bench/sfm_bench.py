"""Accuracy benchmark of the capture front end on a synthetic ring of views (run by hand, not by the tests):

    python -m bench.sfm_bench OUT_DIR [--views 24] [--width 800] [--height 600] [--spp 32] [--known-intrinsics]

Renders the ring (``objcam.synth.views``) into OUT_DIR/views with the true cameras in OUT_DIR/truth (reused when
present), runs :func:`objcam.sfm.frontend.estimate_cameras` on the views, and prints the camera errors against the
truth (centre distance in mm, rotation in degrees: mean, median, max) with the front end's own timings and checks.
Writes OUT_DIR/bench.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np


def camera_errors(estimated: dict, truth: dict) -> dict:
    from objcam.sfm.align import camera_difference

    names = sorted(set(estimated) & set(truth))
    d = np.array([camera_difference(estimated[n], truth[n]) for n in names]).reshape(-1, 2)
    c, r = d[:, 0] * 1000, d[:, 1]
    return {"n": len(names), "centre_mm_mean": float(c.mean()), "centre_mm_median": float(np.median(c)),
            "centre_mm_max": float(c.max()), "rotation_deg_mean": float(r.mean()),
            "rotation_deg_median": float(np.median(r)), "rotation_deg_max": float(r.max()),
            "fx_error_pct": float(np.mean([(estimated[n].fx / truth[n].fx - 1) * 100 for n in names]))}


def main(argv: list[str] | None = None) -> dict:
    from objcam.camera import Camera
    from objcam.sfm.frontend import FrontendOptions, estimate_cameras
    from objcam.synth.views import ViewRingParams, render_views

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--height", type=int, default=600)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--known-intrinsics", action="store_true", help="give SfM the true intrinsics")
    ap.add_argument("--options", default="{}", help="FrontendOptions as JSON")
    a = ap.parse_args(argv)

    out: Path = a.out
    result: dict = {}
    if not (out / "views").is_dir():
        params = ViewRingParams(n_views=a.views, width=a.width, height=a.height, spp=a.spp)
        t = time.perf_counter()
        render_views(out / "views", params, camera_dir=out / "truth")
        result["render_seconds"] = round(time.perf_counter() - t, 1)
        (out / "params.json").write_text(params.model_dump_json(indent=2))
    truth = {p.stem: Camera.load(p) for p in sorted((out / "truth").glob("*.json"))}
    work = out / "work"
    shutil.rmtree(work, ignore_errors=True)
    opts = FrontendOptions.model_validate(json.loads(a.options))
    intr = {"views": next(iter(truth.values()))} if a.known_intrinsics else None
    t = time.perf_counter()
    r = estimate_cameras(work, sorted((out / "views").glob("*.png")), options=opts, intrinsics=intr)
    result["frontend_seconds"] = round(time.perf_counter() - t, 1)
    result["stage_seconds"] = r.seconds
    result["errors"] = camera_errors(r.views, truth)
    result["registered"] = f"{len(r.sfm.registered)}/{len(r.sfm.images)}"
    result["sfm_mean_reprojection_px"] = r.sfm.mean_reprojection_error_px
    result["alignment"] = {k: v for k, v in r.alignment.items() if k != "sim_matrix"}
    result["bundle"] = r.bundle
    result["calibration"] = r.calibration
    result["checks"] = r.summary()
    (out / "bench.json").write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "checks"}, indent=2))
    print(r.summary())
    return result


if __name__ == "__main__":
    main()
