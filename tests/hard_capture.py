"""One tiny hard-suite capture (bench/hard), shared by tests/test_bench_hard.py and tests/test_gi_reference.py: the
torus (albedo 0.8 on 0.5) under the lamp 30 deg up at rotation 0, one 32 x 32 render at 64 spp and max_depth 3,
written by the suite's capture writer and run by objcam up to evaluate (bench.hard.__main__.run_capture)."""

from __future__ import annotations

from pathlib import Path


def tiny_hard_capture(root: Path, elevation_deg: float) -> tuple[Path, list[dict]]:
    """(the capture folder ``root``/cap, its target records from run_capture) for a camera ``elevation_deg`` up."""
    from bench.hard.__main__ import run_capture
    from bench.hard.capture import cached_render, camera_for
    from bench.hard.design import Case, Geometry
    from bench.hard.lighting import Lighting
    from bench.hard.objects import make_object, write_ply

    geo = Geometry("torus", float(elevation_deg), 0.8, 0.5)
    case = Case(Lighting("lamp", "lamp30", 30.0), 0.0, geo)
    mesh = root / "torus.ply"
    write_ply(mesh, *make_object("torus"))
    camera = camera_for(geo, 32)
    renders = {case.name: cached_render(case, mesh, camera, root / "renders", spp=64, max_depth=3)}
    cap = root / "cap"
    return cap, run_capture(cap, geo, [case], renders, camera)
