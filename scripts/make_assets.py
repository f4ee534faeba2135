"""Rebuild objcam/assets/ (provenance record; setup does not run this).

    .venv/bin/python scripts/make_assets.py [--blender-data DIR]

Environment maps: the CC0 HDRI Haven maps (Greg Zaal) that Blender ships as studio-light worlds, taken from
Debian's ``blender-data`` package (``apt-get download blender-data && dpkg -x blender-data_*.deb x``; the maps
are in x/usr/share/blender/datafiles/studiolights/world/, 512x1024 float EXR). Without --blender-data the
script downloads and unpacks the package itself into a temporary folder.

Blender's equirectangular convention (studiolight.cc ``direction_to_equirect`` and Cycles'
``direction_to_equirectangular``, world z up): u = (atan2(d.y, d.x) - pi) / (-2 pi), v = 1 - acos(d.z) / pi, with
v = 1 at the top row of the file: exactly the standard lat-long file convention objcam reads and writes
(data_layout.md; row 0 the zenith, the centre column looks along +x, u grows clockwise seen from above). The
maps are read onto objcam's internal grid (objcam.envmap.read_latlong: a whole-texel column permutation, no
resampling), area-averaged there (objcam.envmap.area_downsample, solid-angle exact) to 128 x 256 and written back
in the standard convention (objcam.envmap.write_latlong) as a float32 zip EXR (pixels are reproducible bit for bit; OpenImageIO stamps a capture date in the header). Bundled:
forest, courtyard, sunset, city, sunrise; the package's other three, interior, night and studio, are not objcam's:
they are written the same way into bench/hard/envmaps/ for the hard suite's held-out design (bench/hard/design.py),
lighting objcam was never tuned on.

Bunny: the Stanford bunny (Stanford 3D Scanning Repository) as shipped with pymeshlab's test data
(pymeshlab/tests/sample_meshes/bunny.obj: closed, 2-manifold, 56k faces, y up), decimated by quadric edge
collapse to ~8k faces (topology preserved), turned to z up by a proper rotation (+90 deg about x), centred on
the origin in x and y, resting on z = 0 and scaled to a height of 1 (unitless; synth scales it), written as
binary PLY.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from objcam.envmap import area_downsample, read_latlong, write_latlong  # noqa: E402

ASSETS = ROOT / "objcam" / "assets"
ENVMAPS = ("forest", "courtyard", "sunset", "city", "sunrise")
HELD_OUT = ("interior", "night", "studio")  # the bench's held-out lighting, not objcam's assets
HELD_OUT_DIR = ROOT / "bench" / "hard" / "envmaps"
HEIGHT = 128
BUNNY_FACES = 8000


def fetch_blender_data(tmp: Path) -> Path:
    subprocess.run(["apt-get", "download", "blender-data"], cwd=tmp, check=True)
    deb = next(tmp.glob("blender-data_*.deb"))
    subprocess.run(["dpkg", "-x", str(deb), "x"], cwd=tmp, check=True)
    return tmp / "x"


def make_envmaps(blender_root: Path) -> None:
    src = blender_root / "usr/share/blender/datafiles/studiolights/world"
    for name in ENVMAPS + HELD_OUT:
        folder = HELD_OUT_DIR if name in HELD_OUT else ASSETS / "envmaps"
        folder.mkdir(parents=True, exist_ok=True)
        env = read_latlong(src / f"{name}.exr")[..., :3].astype(np.float64)
        env = np.nan_to_num(np.maximum(env, 0.0))
        small = area_downsample(env, HEIGHT).astype(np.float32)
        write_latlong(folder / f"{name}.exr", small)
        (folder / f"{name}.exr").chmod(0o644)  # atomic writes create 0600 files
        print(f"{name}: {env.shape} -> {small.shape}, mean {small.mean(axis=(0, 1))}")


def make_bunny() -> None:
    import pymeshlab

    sample = Path(pymeshlab.__file__).parent / "tests" / "sample_meshes" / "bunny.obj"
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(sample))
    ms.apply_filter("meshing_decimation_quadric_edge_collapse", targetfacenum=BUNNY_FACES, preservetopology=True,
                    preservenormal=True, qualitythr=0.5)
    m = ms.current_mesh()
    v = np.asarray(m.vertex_matrix(), dtype=np.float64)
    f = np.asarray(m.face_matrix(), dtype=np.uint32)
    v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)  # +90 deg about x: y up -> z up (no mirror)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v[:, :2] -= (lo[:2] + hi[:2]) / 2
    v[:, 2] -= lo[2]
    v /= hi[2] - lo[2]
    from objcam.synth.assets import write_ply

    write_ply(ASSETS / "bunny.ply", v.astype(np.float32), f)
    (ASSETS / "bunny.ply").chmod(0o644)
    print(f"bunny: {len(v)} vertices, {len(f)} faces")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--blender-data", type=Path, help="folder where blender-data's .deb was unpacked (dpkg -x)")
    args = ap.parse_args()
    make_bunny()
    if args.blender_data:
        make_envmaps(args.blender_data)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            make_envmaps(fetch_blender_data(Path(tmp)))


if __name__ == "__main__":
    main()
