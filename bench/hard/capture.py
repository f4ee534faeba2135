"""Write a geometry configuration's renders as a known-geometry capture exactly per data_layout.md: capture.toml,
object.ply, targets/<name>.exr + .json (one per lighting x noise level), truth/truth.json and
truth/<render>/envmap.exr. Renders are cached (``renders/``) so a rerun only re-solves.

Noise: zero-mean Gaussian of ``level`` x the median pixel (over the positive channel values of the clean render),
per pixel and channel, negatives KEPT (what black-level subtraction and read noise leave); capture.toml's
``noise_sigma`` is hypot(level, the render's own relative noise at the median pixel:
bench.hard.scene.median_pixel_noise), both relative to the median pixel.
"""

from __future__ import annotations

import json
import math
import sys
import time
import zlib
from pathlib import Path

import numpy as np

from bench.hard.design import NOISES, Case, Geometry
from bench.hard.lighting import file_columns, make_envmap
from bench.hard.objects import make_object, write_ply
from bench.hard.scene import look_at_camera, render

DISTANCE = 0.4  # metres from the camera to the point it looks at
AZIMUTH = -90.0  # the camera stands on the -y side
RENDER_VERSION = "v4"  # part of the render cache's key: bump when bench/hard/scene.py changes what it renders
# (v3: the envmap handed to Mitsuba in the contract's box form, bench.hard.scene.contract_bitmap; v4: the render
# noise measured at the median pixel, bench.hard.scene.median_pixel_noise)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def camera_for(geo: Geometry, size: int) -> dict:
    """The configuration's camera JSON: elevation from the design, looking at the object's axis at 2 cm."""
    return look_at_camera(geo.elevation_deg, AZIMUTH, DISTANCE, (0.0, 0.0, 0.02), size)


def cached_render(case: Case, mesh: Path, camera: dict, cache: Path, spp: int, max_depth: int) -> dict:
    """{image (h, w, 3), mc (relative render noise), envmap (H, 2H, 3), rotation, seconds}; from ``cache`` when
    rendered before with the same parameters."""
    key = f"{case.name}-{case.geometry.key}-{camera['width']}px-{spp}spp-d{max_depth}-{RENDER_VERSION}"
    path = cache / f"{key}.npz"
    env, rot = make_envmap(case.light, case.rotation_deg)
    if path.is_file():
        d = np.load(path)
        return {"image": d["image"], "mc": float(d["mc"]), "envmap": env, "rotation": rot,
                "seconds": float(d["seconds"]), "cached": True}
    t0 = time.perf_counter()
    seed = zlib.crc32(key.encode()) % 100000
    img, mc = render(mesh, camera, env, case.geometry.albedo_object, case.geometry.albedo_support, spp, seed,
                     max_depth)
    dt = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, image=img, mc=mc, seconds=dt)
    return {"image": img, "mc": mc, "envmap": env, "rotation": rot, "seconds": dt, "cached": False}


def add_noise(clean: np.ndarray, level: float, seed: int) -> np.ndarray:
    """clean + N(0, (level x median positive value)^2) per pixel and channel, negatives kept. (h, w, 3) float32."""
    pos = clean[clean > 0]
    sigma = level * (float(np.median(pos)) if pos.size else 1.0)
    rng = np.random.default_rng(seed)
    return (clean + rng.normal(0.0, sigma, clean.shape)).astype(np.float32)


def write_capture(root: Path, geo: Geometry, group: list[Case], renders: dict[str, dict], camera: dict,
                  keep: set[str] | None = None) -> list[dict]:
    """Write the capture for ``geo`` holding every case of ``group`` at every noise level (or only the targets
    named in ``keep``); returns the targets' records {target, case, noise, noise_sigma, min, negative_pixels}."""
    from objcam.image_io import write_exr

    import shutil

    shutil.rmtree(root / "targets", ignore_errors=True)  # targets left out of this write must not linger
    (root / "targets").mkdir(parents=True)
    v, f = make_object(geo.object)
    write_ply(root / "object.ply", v, f)
    toml = ["[scene]", 'object = "object.ply"', 'support = "plane"', "plane_size = 20.0", "",
            "[albedo]", f"object = {geo.albedo_object}", f"support = {geo.albedo_support}", ""]
    truth = {"flavour": "known-geometry", "writer": "bench/hard (independent Mitsuba scene)", "envmaps": {},
             "targets": {}, "albedo": {"object": {"rgb": [geo.albedo_object] * 3},
                                       "support": {"rgb": [geo.albedo_support] * 3}}}
    records = []
    for case in group:
        r = renders[case.name]
        env_rel = f"truth/{case.name}/envmap.exr"
        (root / "truth" / case.name).mkdir(parents=True, exist_ok=True)
        write_exr(root / env_rel, file_columns(r["envmap"]))  # the standard file convention
        write_exr(root / "truth" / case.name / "clean.exr", r["image"])
        for noise in NOISES:
            name = case.target(noise)
            img = add_noise(r["image"], noise, zlib.crc32(name.encode()))
            sigma = math.hypot(noise, r["mc"])
            records.append({"target": name, "case": case.name, "noise": noise, "noise_sigma": sigma,
                            "render_noise": r["mc"], "min": float(img.min()),
                            "negative_pixels": int((img < 0).any(axis=-1).sum())})
            truth["envmaps"][name] = env_rel
            truth["targets"][name] = {"rotation_deg": r["rotation"], "noise_level": noise,
                                      "render_noise_sigma": r["mc"], "clean_image": f"truth/{case.name}/clean.exr",
                                      "lighting": case.light.name}
            if keep is not None and name not in keep:
                continue
            write_exr(root / "targets" / f"{name}.exr", img)
            (root / "targets" / f"{name}.json").write_text(json.dumps(camera, indent=1))
            toml += ["[[targets]]", f'name = "{name}"', f'image = "targets/{name}.exr"',
                     f'camera = "targets/{name}.json"', f"noise_sigma = {sigma:.6g}", ""]
    (root / "truth" / "truth.json").write_text(json.dumps(truth, indent=1))
    (root / "capture.toml").write_text("\n".join(toml))
    return records
