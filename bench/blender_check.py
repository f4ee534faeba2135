"""``make bench-blender``: the exported Blender script run headless in Blender (issue 23), against the standard
lat-long convention and against Mitsuba's render of the same export. Needs ``blender`` on PATH (Debian 12:
``apt-get install blender``, 3.4); CI does not install it, so this is a bench, not a test: without Blender it
stops with a one-line error (exit 2), never a silent skip.

1. **World orientation.** An envmap written here from data_layout.md's formula alone (u = 0.5 - atan2(y, x) /
   (2 pi), v = theta / pi; a seeded random pattern of texels and one bright lamp texel at azimuth 60 deg,
   elevation 30 deg), given to objcam.export.blender's script with no mesh and a 32 x 32, 40 deg camera looking at
   the lamp. Cycles renders the world; the expected image is the formula evaluated at 32 x 32 sub-pixel rays per
   pixel (box filter) through objcam.camera.Camera.rays. Reported: relative L2 of the render against it, against
   the mirrored convention (u = 0.5 + atan2 / 2 pi: the error issue 23 found), and the lamp's pixel.
2. **The exported scene.** A small synthetic capture (a sphere on a checker support under courtyard, direct light,
   40 x 40 pixels) run through solve and ``objcam export``, twice: every albedo known, and every albedo unknown
   (the support and object textures baked from the solve, objcam.export.bake). Blender renders
   ``blender_scene.py``'s camera with Cycles, two seeds; Mitsuba renders ``mitsuba/t0.xml``, two seeds; both
   compared with the solve's prediction: relative L2, its Monte Carlo noise (half the seeds' difference), and the
   bias beyond it (sqrt(rel^2 - noise^2)); and Blender against Mitsuba (the noise of both).

    python -m bench.blender_check [--write] [--spp 1024]
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.sections import invocation, write_section

LAMP_AZ, LAMP_EL = 60.0, 30.0  # degrees, world z up, azimuth from +x towards +y
ENV_H = 16


def _blender() -> str:
    exe = shutil.which("blender")
    if exe is None:
        sys.exit("bench.blender_check: no `blender` on PATH: install it (Debian 12: apt-get install blender) to run "
                 "this bench")
    return exe


def _render(script: Path, out: Path, seed: int) -> np.ndarray:
    """Run ``script`` headless in Blender, rendering its first camera into ``out`` (linear EXR)."""
    from objcam.image_io import read_exr

    cmd = [_blender(), "-b", "--factory-startup", "--python-exit-code", "1", "--python", str(script), "--",
           "--render", str(out), "--seed", str(seed)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if r.returncode != 0 or not out.is_file():
        tail = (r.stdout + r.stderr).strip().splitlines()[-5:]
        raise RuntimeError(f"blender failed on {script}: " + " | ".join(tail))
    return read_exr(out)[..., :3].astype(np.float64)


def _standard_texel(d: np.ndarray, h: int, mirrored: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of world directions ``d`` (..., 3) in an h x 2h standard lat-long image (data_layout.md's
    formula, restated here; ``mirrored``: the convention issue 23 replaced)."""
    theta = np.arccos(np.clip(d[..., 2], -1.0, 1.0))
    phi = np.arctan2(d[..., 1], d[..., 0])
    u = 0.5 + phi / (2 * np.pi) if mirrored else 0.5 - phi / (2 * np.pi)
    col = np.floor(np.mod(u, 1.0) * 2 * h).astype(np.int64) % (2 * h)
    row = np.clip(np.floor(theta / np.pi * h).astype(np.int64), 0, h - 1)
    return row, col


def world_orientation(tmp: Path, spp: int) -> dict:
    from objcam.camera import Camera, look_at
    from objcam.export.blender import write_blender_script
    from objcam.image_io import write_exr

    rng = np.random.default_rng(0)
    env = rng.uniform(0.2, 1.0, (ENV_H, 2 * ENV_H, 3))
    az, el = math.radians(LAMP_AZ), math.radians(LAMP_EL)
    lamp = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    r, c = _standard_texel(lamp, ENV_H)
    env[r, c] = 50.0
    write_exr(tmp / "env.exr", env.astype(np.float32))
    n, fov = 32, 40.0
    f = n / 2 / math.tan(math.radians(fov / 2))
    cam = Camera(width=n, height=n, fx=f, fy=f, cx=(n - 1) / 2, cy=(n - 1) / 2,
                 world_from_camera=look_at(np.zeros(3), lamp).tolist())
    script = write_blender_script(tmp / "world.py", "env.exr", [], {"look": cam}, max_depth=2, samples=spp)
    halves = [_render(script, tmp / f"world{s}.exr", s) for s in (1, 2)]
    render = (halves[0] + halves[1]) / 2
    k = 32  # sub-pixel rays per side: the box filter's average (8 leaves 1.8% at the lamp texel's edges)
    s = (np.arange(k) + 0.5) / k - 0.5
    vv, uu = np.mgrid[0:n, 0:n]
    want = {False: np.zeros((n, n, 3)), True: np.zeros((n, n, 3))}
    for dy in s:
        for dx in s:
            _, d = cam.rays(uu + dx, vv + dy)
            for mir in want:
                rr, cc = _standard_texel(d, ENV_H, mir)
                want[mir] += env[rr, cc] / k**2
    rel = {mir: float(np.linalg.norm(render - w) / np.linalg.norm(w)) for mir, w in want.items()}
    noise = float(np.linalg.norm(halves[0] - halves[1]) / 2 / np.linalg.norm(want[False]))

    def centroid(img: np.ndarray) -> list[float]:  # of the lamp texel's pixels (above half its radiance)
        w = (img.mean(axis=2) > 25.0) * img.mean(axis=2)
        return [round(float((w * uu).sum() / w.sum()), 2), round(float((w * vv).sum() / w.sum()), 2)]

    return {"relative_l2": rel[False], "relative_l2_mirrored": rel[True], "noise": noise,
            "bias": math.sqrt(max(rel[False] ** 2 - noise**2, 0.0)), "lamp_centroid": centroid(render),
            "lamp_centroid_expected": centroid(want[False]),
            "lamp_radiance": float(render.mean(axis=2).max()), "lamp_radiance_expected": 50.0}


def _export(tmp: Path, unknown: bool) -> Path:
    from objcam.pipeline.cli import main
    from objcam.synth.capture import SynthParams, synthesize

    cap = tmp / ("unknown" if unknown else "known") / "cap"
    synthesize(cap, SynthParams(object="sphere", object_height=0.04, envmap="courtyard", envmap_height=16,
                                cameras=[{"width": 40, "height": 40, "distance": 0.25, "elevation_deg": 55.0}],
                                support_albedo="checker", texture_size=64, texture_extent=0.3, spp=64, max_depth=2,
                                noise=False, object_albedo_known=not unknown, support_albedo_known=not unknown))
    sets = ["transport.env_height=8", "transport.model=direct", "solve.prior=smooth"]
    if main(["run", str(cap), "-q", "--until", "solve", *[a for s in sets for a in ("--set", s)]]) != 0:
        raise RuntimeError(f"objcam run failed on {cap}")
    out = cap.parent / "export"
    if main(["export", str(cap), str(out)]) != 0:
        raise RuntimeError(f"objcam export failed on {cap}")
    return cap


def _compare(a: np.ndarray, b: np.ndarray, pred: np.ndarray) -> dict:
    used = np.any(pred != 0, axis=2)
    norm = np.linalg.norm(pred[used])
    mean = (a + b) / 2
    rel = float(np.linalg.norm(mean[used] - pred[used]) / norm)
    noise = float(np.linalg.norm(a[used] - b[used]) / 2 / norm)
    return {"relative_l2": rel, "noise": noise, "bias": math.sqrt(max(rel**2 - noise**2, 0.0))}


def _pair(a: list[np.ndarray], b: list[np.ndarray]) -> dict:
    """Two renderers' two-seed renders against each other: the noise of both means counts."""
    ma, mb = (a[0] + a[1]) / 2, (b[0] + b[1]) / 2
    used = np.any(mb != 0, axis=2)
    norm = np.linalg.norm(mb[used])
    rel = float(np.linalg.norm(ma[used] - mb[used]) / norm)
    noise = float(np.hypot(np.linalg.norm(a[0][used] - a[1][used]), np.linalg.norm(b[0][used] - b[1][used])) / 2
                  / norm)
    return {"relative_l2": rel, "noise": noise, "bias": math.sqrt(max(rel**2 - noise**2, 0.0))}


def exported_scene(tmp: Path, unknown: bool, spp: int) -> dict:
    from objcam.image_io import read_exr
    from objcam.scene import use_mitsuba

    cap = _export(tmp, unknown)
    out = cap.parent / "export"
    pred = read_exr(cap / "objcam" / "solve" / "t0" / "prediction.exr")[..., :3].astype(np.float64)
    t = time.perf_counter()
    bl = [_render(out / "blender_scene.py", cap.parent / f"blender{s}.exr", s) for s in (1, 2)]
    t_bl = time.perf_counter() - t
    mi = use_mitsuba()
    scene = mi.load_file(str(out / "mitsuba" / "t0.xml"))
    t = time.perf_counter()
    mt = [np.asarray(mi.render(scene, seed=s, spp=spp), np.float64)[..., :3] for s in (1, 2)]
    t_mt = time.perf_counter() - t
    blender = _compare(*bl, pred)
    return {"albedo": "unknown (baked)" if unknown else "known", "blender": blender, "mitsuba": _compare(*mt, pred),
            "blender_vs_mitsuba": _pair(bl, mt), "seconds_blender": t_bl,
            "seconds_mitsuba": t_mt}


def _markdown(world: dict, scenes: list[dict], spp: int, version: str) -> str:
    lines = [f"Made by {invocation('bench.blender_check', None)} with {version}, {spp} samples per pixel "
             "(2 cores shared with other jobs: times are inflated).", "",
             "World orientation (an envmap written from data_layout.md's formula, rendered by Blender's world "
             f"through the exported script; lamp at azimuth {LAMP_AZ:.0f} deg, elevation {LAMP_EL:.0f} deg):", "",
             "| render against | relative L2 |", "|---|---:|",
             f"| the standard convention | {world['relative_l2']:.4f} (noise {world['noise']:.4f}, bias "
             f"{world['bias']:.4f}) |",
             f"| the mirrored convention (before issue 23) | {world['relative_l2_mirrored']:.4f} |", "",
             f"Lamp texel's pixels: centroid {world['lamp_centroid']} (formula: {world['lamp_centroid_expected']}), "
             f"peak radiance {world['lamp_radiance']:.2f} (formula {world['lamp_radiance_expected']:.2f}).", "",
             "The exported scene (sphere on a checker support, 40 x 40 pixels, direct light): Blender (Cycles, "
             "`blender_scene.py`) and Mitsuba (`mitsuba/t0.xml`) against the solve's prediction; bias = "
             "sqrt(relative L2^2 - noise^2), noise from two seeds.", "",
             "| albedo | renderer | relative L2 | noise | bias | seconds (2 renders) |",
             "|---|---|---:|---:|---:|---:|"]
    for s in scenes:
        for key, name, sec in (("blender", "Blender", s["seconds_blender"]), ("mitsuba", "Mitsuba",
                                                                              s["seconds_mitsuba"])):
            m = s[key]
            lines.append(f"| {s['albedo']} | {name} | {m['relative_l2']:.4f} | {m['noise']:.4f} | {m['bias']:.4f} | "
                         f"{sec:.1f} |")
        m = s["blender_vs_mitsuba"]
        lines.append(f"| {s['albedo']} | Blender against Mitsuba | {m['relative_l2']:.4f} | {m['noise']:.4f} | "
                     f"{m['bias']:.4f} | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=1024, help="samples per pixel of every render")
    ap.add_argument("--write", action="store_true", help="write the block into bench/results.md")
    args = ap.parse_args(argv)
    exe = _blender()
    version = subprocess.run([exe, "-b", "--version"], capture_output=True, text=True).stdout.splitlines()[0]
    with tempfile.TemporaryDirectory(prefix="objcam_blender_") as d:
        tmp = Path(d)
        world = world_orientation(tmp, args.spp)
        print("world:", world, flush=True)
        scenes = []
        for unknown in (False, True):
            scenes.append(exported_scene(tmp, unknown, args.spp))
            print(scenes[-1], flush=True)
    body = _markdown(world, scenes, args.spp, version.strip())
    print(body)
    if args.write:
        write_section("blender", body, "Blender: the exported script run headless (issue 23)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
