"""The hard suite's joint-solve family (issue 29): the support's albedo left unknown, the object's known, three
illuminations seen from one camera, rendered by the suite's own Mitsuba scene (bench/hard/scene.py), not objcam's.

    python -m bench.hard.joint_family [--out bench/out/joint] [--size 128] [--spp 1024] [--noise 0.02]
                                      [--set STAGE.PARAM=VALUE ...]

Two albedo pairs (a dark object of 0.05 on a support of 0.8, and the reverse), each written twice per
data_layout.md: with the support's albedo unknown (``[albedo]`` names only the object) and with it given (the
reference for the envmap's SSIM). Lighting: HDRIs objcam does not bundle (Blender's CC0 studio lights ``night``,
``interior``, ``studio`` from Debian's blender-data, found under /usr/share/blender or ``--hdri-dir``), else the
suite's procedural room, window and sun (bench/hard/lighting.py). Reported per capture and target: the support's
albedo (median and mean over the estimated pixels, no scale fitted), target / prediction over the object's pixels
of known albedo, the envmap's SSIM with the support unknown and given, and evaluate's albedo figures.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import zlib
from pathlib import Path

import numpy as np

from bench.hard.capture import DISTANCE, add_noise, log
from bench.hard.lighting import HEIGHT, Lighting, file_columns, make_envmap
from bench.hard.objects import make_object, write_ply
from bench.hard.scene import look_at_camera, render

BLENDER_HDRIS = ("night", "interior", "studio")
HDRI_DIRS = (Path("/usr/share/blender/datafiles/studiolights/world"),)
PAIRS = ((0.05, 0.8), (0.8, 0.05))  # (object known, support unknown)
FALLBACK = (Lighting("room", "room2"), Lighting("window", "window"), Lighting("sun", "sun55", 55.0))


def lightings(hdri_dir: Path | None, procedural: bool = False) -> list[tuple[str, np.ndarray]]:
    """[(name, envmap (HEIGHT, 2 HEIGHT, 3) float32)] on the suite's internal grid (bench/hard/lighting.py): Blender's
    HDRIs (standard lat-long files, converted by ``file_columns``) area-averaged to it (negative compression noise set
    to 0) when found (and not ``procedural``), else the procedural fallback."""
    from objcam.image_io import read_exr

    dirs = [] if procedural else [hdri_dir] if hdri_dir else list(HDRI_DIRS)
    for d in dirs:
        if d and all((d / f"{n}.exr").is_file() for n in BLENDER_HDRIS):
            out = []
            for n in BLENDER_HDRIS:
                # the file is in the standard convention, the scene renderer reads the internal grid (issue 23)
                e = file_columns(np.clip(read_exr(d / f"{n}.exr")[..., :3].astype(np.float64), 0, None))
                f = e.shape[0] // HEIGHT
                e = e.reshape(HEIGHT, f, 2 * HEIGHT, f, 3).mean(axis=(1, 3))  # a box over f x f equal-size texels
                out.append((n, e.astype(np.float32)))
            return out
    log("Blender's HDRIs not found: the procedural room, window and sun instead")
    return [(lt.name, make_envmap(lt, 0.0)[0]) for lt in FALLBACK]


def render_family(mesh: Path, camera: dict, envs: list[tuple[str, np.ndarray]], albedo_object: float,
                  albedo_support: float, spp: int, cache: Path | None, tag: str = "") -> tuple[list, list]:
    """(images (h, w, 3) float32, relative render noises) of every lighting, by the suite's own Mitsuba scene;
    cached in ``cache`` (None: not cached)."""
    images, mcs = [], []
    for name, env in envs:
        # "-std": renders since the HDRIs are read in the standard convention (earlier ones saw them mirrored);
        # "-box": since the envmap reaches Mitsuba in the contract's box form (bench.hard.scene.contract_bitmap)
        # "-med": since the render noise is measured at the median pixel (bench.hard.scene.median_pixel_noise)
        key = f"{name}-{tag}-{albedo_object:g}on{albedo_support:g}-{camera['width']}px-{spp}spp-std-box-med"
        path = cache / f"{key}.npz" if cache is not None else None
        if path is not None and path.is_file():
            r = np.load(path)
            img, mc = r["image"], float(r["mc"])
        else:
            img, mc = render(mesh, camera, env, albedo_object, albedo_support, spp, zlib.crc32(key.encode()) % 100000)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(path, image=img, mc=mc)
            log(f"  rendered {key}: render noise {100 * mc:.2f}%")
        images.append(img)
        mcs.append(mc)
    return images, mcs


def write_family_capture(root: Path, mesh_v, mesh_f, camera: dict, envs: list[tuple[str, np.ndarray]],
                         images: list[np.ndarray], albedo_object: float, albedo_support: float,
                         support_known: bool, noise: float, mc: float) -> list[str]:
    """One capture per data_layout.md (targets ``<lighting>``, each its own illumination); returns target names."""
    from objcam.image_io import write_exr

    (root / "targets").mkdir(parents=True, exist_ok=True)
    write_ply(root / "object.ply", mesh_v, mesh_f)
    toml = ["[scene]", 'object = "object.ply"', "", "[albedo]", f"object = {albedo_object}"]
    toml += [f"support = {albedo_support}"] if support_known else []
    toml.append("")
    truth = {"flavour": "known-geometry", "writer": "bench/hard/joint_family.py", "envmaps": {}, "targets": {},
             "albedo": {"object": [albedo_object] * 3, "support": {"rgb": [albedo_support] * 3}}}
    names = []
    sigma = math.hypot(noise, mc)
    for (name, env), img in zip(envs, images):
        (root / "truth" / name).mkdir(parents=True, exist_ok=True)
        write_exr(root / "truth" / name / "envmap.exr", file_columns(env))  # the standard file convention
        write_exr(root / "targets" / f"{name}.exr", add_noise(img, noise, zlib.crc32(name.encode())))
        (root / "targets" / f"{name}.json").write_text(json.dumps(camera, indent=1))
        truth["envmaps"][name] = f"truth/{name}/envmap.exr"
        toml += ["[[targets]]", f'name = "{name}"', f'image = "targets/{name}.exr"',
                 f'camera = "targets/{name}.json"', f'illumination = "{name}"', f"noise_sigma = {sigma:.6g}", ""]
        names.append(name)
    (root / "truth" / "truth.json").write_text(json.dumps(truth, indent=1))
    (root / "capture.toml").write_text("\n".join(toml))
    return names


def score(work: Path, target: str) -> dict:
    """Support albedo (no scale fitted), the object's known pixels' target / prediction, evaluate's figures."""
    import cv2

    from objcam.image_io import read_exr
    from objcam.transport import load_transport

    d = work / "solve" / target
    m = json.loads((work / "evaluate" / "metrics.json").read_text())[target]
    out = {k: m.get(k) for k in ("ssim", "relative_rmse", "albedo_relative_rmse", "albedo_scale",
                                 "albedo_relative_rmse_fitted_scale", "albedo_scored_as")}
    sj = json.loads((d / "solve.json").read_text())
    out["scale_ambiguous"] = sj.get("scale_ambiguous")
    if (d / "albedo.exr").is_file():
        a = read_exr(d / "albedo.exr")[..., :3].astype(np.float64)
        mask = cv2.imread(str(d / "albedo_mask.png"), cv2.IMREAD_UNCHANGED) > 127
        out["support_median"] = float(np.median(a[mask].mean(axis=1)))
        out["support_mean"] = float(a[mask].mean())
    else:
        mask = None
    y = read_exr(d / "target.exr")[..., :3].astype(np.float64)
    p = read_exr(d / "prediction.exr")[..., :3].astype(np.float64)
    tr = load_transport(work / "transport", target, load_A=False)
    obj = np.zeros(y.shape[0] * y.shape[1], bool)
    obj[tr.pixel_index] = tr.object_fraction >= 0.999  # wholly the object's: its albedo is known
    obj = obj.reshape(y.shape[:2]) & (p.sum(axis=-1) > 0)
    out["object_pixels"] = int(obj.sum())
    out["object_ratio"] = float(y[obj].sum() / p[obj].sum()) if obj.any() else None
    sup = ~obj & (p.sum(axis=-1) > 0)
    out["support_ratio"] = float(y[sup].sum() / p[sup].sum()) if sup.any() else None
    return out


def main(argv: list[str] | None = None) -> int:
    from objcam.pipeline.engine import Pipeline, parse_overrides

    ap = argparse.ArgumentParser(prog="python -m bench.hard.joint_family", description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/out/joint"))
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--noise", type=float, default=0.02)
    ap.add_argument("--object", default="bunny")
    ap.add_argument("--elevation", type=float, default=35.0)
    ap.add_argument("--hdri-dir", type=Path, default=None)
    ap.add_argument("--pairs", default="0,1", help="indices into PAIRS (development)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.PARAM=VALUE")
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    args = ap.parse_args(argv)
    os.environ.setdefault("OBJCAM_QUIET", "1")
    v, f = make_object(args.object)
    mesh = args.out / "meshes" / f"{args.object}.ply"
    mesh.parent.mkdir(parents=True, exist_ok=True)
    write_ply(mesh, v, f)
    camera = look_at_camera(args.elevation, -90.0, DISTANCE, (0.0, 0.0, 0.02), args.size)
    envs = lightings(args.hdri_dir)
    rows = []
    for pi in (int(i) for i in args.pairs.split(",")):
        a_obj, a_sup = PAIRS[pi]
        images, mcs = render_family(mesh, camera, envs, a_obj, a_sup, args.spp, args.out / "renders",
                                    f"{args.object}-el{args.elevation:g}")
        for known in (False, True):
            root = args.out / "captures" / f"{a_obj:g}on{a_sup:g}-{'given' if known else 'unknown'}"
            names = write_family_capture(root, v, f, camera, envs, images, a_obj, a_sup, known, args.noise,
                                         max(mcs))
            tag = "objcam" if not args.sets else "objcam-" + str(zlib.crc32(" ".join(args.sets).encode()))
            Pipeline(root, root / tag, overrides=parse_overrides(list(args.sets)), quiet=True).run(until="evaluate")
            for n in names:
                row = {"pair": f"{a_obj:g} on {a_sup:g}", "support": "given" if known else "unknown", "target": n,
                       **score(root / tag, n)}
                rows.append(row)
                log(json.dumps(row, default=float))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
