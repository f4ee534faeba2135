"""``objcam export CAPTURE OUT``: the recovered envmaps, meshes, cameras and ready-made Mitsuba and Blender scenes
(objcam.export)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_export_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder (already run)")
    p.add_argument("out", type=Path, help="export folder (new, empty, or an earlier export)")
    p.add_argument("--work", type=Path, default=None, help="artifact folder the run used (default CAPTURE/objcam)")
    p.add_argument("--upsample", type=int, default=1, metavar="N",
                   help="repeat every envmap texel N x N times in the EXR/HDR files (for display; default 1)")
    p.add_argument("--spp", type=int, default=256, help="the Mitsuba scenes' default samples per pixel")


def run_export(args) -> int:
    from rich.console import Console

    from objcam.errors import ObjcamError
    from objcam.export.run import ExportOptions, export_capture

    if args.upsample < 1 or args.upsample > 64:
        raise ObjcamError(f"--upsample {args.upsample}: give 1 to 64")
    if not (args.capture / "capture.toml").is_file():
        raise ObjcamError("no capture.toml", args.capture, "give the capture folder you ran")
    work = args.work if args.work is not None else args.capture / "objcam"
    rec = export_capture(work, args.out, ExportOptions(upsample=args.upsample, spp=max(1, args.spp)))
    con = Console(highlight=False)
    con.print(f"exported {len(rec['files'])} files to {args.out}")
    for t, r in rec["targets"].items():
        con.print(f"  {t}: {args.out / r['envmap']}, {args.out / r['mitsuba']}")
    con.print(f"  meshes: {args.out / 'meshes'}; cameras: {args.out / 'colmap'}, {args.out / 'transforms.json'}; "
              f"Blender: {args.out / 'blender_scene.py'}")
    for w in rec["warnings"]:
        con.print(f"  [yellow]warning[/]: {w}")
    return 0
