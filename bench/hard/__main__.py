"""``make bench BENCH=hard``: the hard-case suite (issue 22), runnable as ``python -m bench.hard``.

    python -m bench.hard [--quick] [--write] [--out bench/out/hard] [--size 128] [--spp 2048] [--max-depth -1]
    python -m bench.hard --design held-out --out bench/out/hard-held-out [--write]

Renders every case of bench/hard/design.py with the suite's own Mitsuba scene (bench/hard/scene.py: path tracing,
interreflections to ``max_depth``, a multi-jittered sampler), writes one known-geometry capture per geometry
configuration (bench/hard/capture.py), runs objcam on it with default parameters up to ``evaluate`` (the
``analysis`` and ``report`` stages of ``objcam run`` do not change the numbers) and scores every target
(bench/hard/score.py). Renders are cached in OUT/renders and objcam's stages in each capture, so a rerun only
redoes what changed. A capture the scene stage refuses for negative pixels is rerun with the targets that have
none, and the others are recorded as refused (never clipped). ``--write`` puts the block into bench/results.md
and the raw rows into bench/hard_rows.json (``--quick`` into bench/hard_rows_quick.json). ``--design held-out``:
the held-out design (other objects, cameras, albedos, rotations and lightings; bench/hard/design.py), its block
and rows apart (bench/hard_held_out_rows.json).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import time
from pathlib import Path

from bench.hard.capture import cached_render, camera_for, log, write_capture
from bench.hard.design import DESIGNS, NOISES, cases
from bench.hard.objects import make_object, write_ply
from bench.hard.report import markdown
from bench.hard.score import target_row
from bench.sections import invocation, write_section

TITLE = "Hard cases (issue 22)"
HELD_OUT_TITLE = "Hard cases held out: objects, cameras, albedos and lighting the suite never had (issue 22)"
REFUSED = "the scene stage refuses negative pixels (zero-mean noise kept, never clipped)"


def run_capture(root: Path, geo, group, renders, camera, sets: tuple[str, ...] = ()) -> list[dict]:
    """Write and run one geometry's capture; returns its target records with ``status`` and, when solved, the
    score (bench.hard.score.target_row). ``sets``: objcam ``--set`` overrides (stage.param=value), run in a work
    folder of their own (``objcam-<hash>``) so the defaults' cache stays; it starts as a copy of the defaults'
    folder when that exists, so the stages the overrides do not change come from the cache (a solve setting
    reruns solve and evaluate only: ~4 min for the suite instead of ~15)."""
    import shutil

    from objcam.errors import ObjcamError
    from objcam.pipeline.engine import Pipeline, parse_overrides

    work = root / ("objcam" if not sets else "objcam-" + hashlib.sha1(" ".join(sets).encode()).hexdigest()[:8])
    if sets and not work.exists() and (root / "objcam").is_dir():
        shutil.copytree(root / "objcam", work, ignore=shutil.ignore_patterns(".lock"))

    records = write_capture(root, geo, group, renders, camera)
    status = {r["target"]: ("ok", "") for r in records}
    first_message = ""
    cached: dict[str, bool] = {}
    for attempt in range(2):
        try:
            # issue 28: a time read from a stage that came from the cache is an earlier run's; flag it
            pipe = Pipeline(root, work, overrides=parse_overrides(list(sets)), quiet=True)
            cached = {rep.stage: rep.status == "cached" for rep in pipe.run(until="evaluate")}
            break
        except ObjcamError as e:
            msg = " ".join(str(e).split()).replace(f"{root.resolve()}/", "")
            keep = {r["target"] for r in records if r["negative_pixels"] == 0}
            if attempt == 0 and "negative" in msg and keep and len(keep) < len(records):
                # today's scene stage refuses zero-mean noise: solve the targets without negatives, record the rest
                log(f"    refused ({msg[:100]}); rerunning the {len(keep)} targets without negative pixels")
                for r in records:
                    if r["target"] not in keep:
                        status[r["target"]] = ("refused", REFUSED)
                first_message = msg
                write_capture(root, geo, group, renders, camera, keep=keep)
                continue
            kind = "refused" if "negative" in msg else "failed"
            first_message = first_message or msg
            for r in records:
                if status[r["target"]][0] == "ok":
                    status[r["target"]] = (kind, REFUSED if kind == "refused" else f"objcam: {msg}")
            break
    out = []
    for r in records:
        st, err = status[r["target"]]
        row = {**r, "status": st, "error": err, "objcam_message": first_message if st != "ok" else ""}
        if st == "ok":
            row.update(target_row(work, root, r["target"]))
            row.update(a_cached=cached.get("transport", False), solve_cached=cached.get("solve", False))
        out.append(row)
    return out


def header_lines(label: str, n_renders: int, n_geometries: int, n_rows: int, size: int, spp: int,
                 max_depth: int, wall: float, render_s: float | None, made_by: str) -> list[str]:
    import mitsuba

    return [f"{made_by}: the **{label}** suite"
            + (" (the development subset: 4 renders at 64 x 64, 256 spp; not the suite's numbers)"
               if label == "quick" else "") + ".", "",
            f"Machine: {os.cpu_count()} cores (shared with other work), Python {platform.python_version()}, Mitsuba "
            f"{mitsuba.__version__}. Wall time {wall / 60:.1f} min"
            + ("" if render_s is None else f" ({render_s / 60:.1f} min of new renders)") + ".", "",
            f"Design (bench/hard/design.py): {n_renders} renders (lighting x rotation, each on one of "
            f"{n_geometries} geometries: object, camera elevation, albedo pair) x noise "
            f"{', '.join(f'{100 * n:g}%' for n in NOISES)} = {n_rows} targets. Targets path-traced by the suite's own "
            f"Mitsuba scene (not objcam's scene builder or A), max_depth {max_depth}, {spp} spp (multi-jittered), "
            f"{size} x {size}; zero-mean Gaussian noise of the stated level x the median pixel, negatives kept; "
            "solved by objcam with default parameters and known albedo (`objcam run` up to evaluate)."]


def regenerate(args) -> int:
    """The block again from committed rows (``--from-rows``), without rendering or solving."""
    d = json.loads(args.from_rows.read_text())
    rows = d["rows"]
    if args.rescore:
        for r in rows:
            if r["status"] == "ok":
                root = args.out / "captures" / f"{r['geometry']}-{d['size']}px-{d['spp']}spp"
                keep = {k: r[k] for k in ("a_seconds", "a_summary", "solve_seconds") if k in r}
                r.update(target_row(root / "objcam", root, r["target"]), **keep)
        if args.write:
            args.from_rows.write_text(json.dumps(d, indent=1, default=float))
    for r in rows:  # rows of the first runs held objcam's message, naming a path, as their error
        if r["status"] == "refused":
            r["error"] = REFUSED
    header = header_lines(d["label"], len({r["case"] + r["geometry"] for r in rows}),
                          len({r["geometry"] for r in rows}), len(rows), d["size"], d["spp"], d["max_depth"],
                          d["wall_seconds"], d.get("render_seconds"), d.get("made_by", "`python -m bench.hard`"))
    text = markdown(rows, header, NOISES)
    print(text)
    if args.write:
        held = d["label"] == "held-out"
        write_section("hard_held_out" if held else "hard", text, HELD_OUT_TITLE if held else TITLE, args.results)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.hard", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the development subset (4 renders, 64 x 64, 256 spp)")
    ap.add_argument("--out", type=Path, default=Path("bench/out/hard"))
    ap.add_argument("--results", type=Path, default=Path("bench/results.md"))
    ap.add_argument("--size", type=int, default=None, help="image side, pixels (default 128; quick 64)")
    ap.add_argument("--spp", type=int, default=None, help="samples per pixel (default 2048; quick 256)")
    ap.add_argument("--max-depth", type=int, default=-1,
                    help="Mitsuba's path depth: -1 (default) every bounce, as in a photo; >= 3 truncates the "
                         "interreflections (the suite was rendered at 4 before session 45: two bounces, fewer than "
                         "objcam's A models)")
    ap.add_argument("--only", default="", help="comma-separated lighting names (development)")
    ap.add_argument("--rotations", default="", help="three comma-separated angles in degrees instead of the "
                    "design's (the suite's 0,137,251): a held-out check (e.g. 60,200,310; use its own --out)")
    ap.add_argument("--design", choices=sorted(DESIGNS), default="suite",
                    help="suite (default) or held-out: other objects, cameras, albedos, rotations and lightings, "
                         "none used to choose a parameter (use its own --out)")
    ap.add_argument("--write", action="store_true", help="write the block and the raw rows")
    ap.add_argument("--from-rows", type=Path, default=None,
                    help="regenerate the block from a rows JSON this script wrote (bench/hard_rows.json); no run")
    ap.add_argument("--rescore", action="store_true",
                    help="with --from-rows: recompute every solved row's scores from the artifacts under --out "
                         "(after a change to bench/hard/score.py; statuses and times stay the run's)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                    help="an objcam parameter for every case (repeatable), e.g. solve.ls_noise_factor=3: measures a "
                         "setting across the suite (its own work folder per capture; rows to rows_<label>-<hash>.json)")
    args = ap.parse_args(argv)
    if args.from_rows:
        return regenerate(args)
    os.environ.setdefault("OBJCAM_QUIET", "1")
    size = args.size or (64 if args.quick else 128)
    spp = args.spp or (256 if args.quick else 2048)
    design = DESIGNS[args.design]
    if args.quick and design.name != "suite":
        ap.error("--quick is the suite's development subset")
    rotations = tuple(float(a) for a in args.rotations.split(",")) if args.rotations else None
    todo = [c for c in cases(args.quick, rotations, design) if not args.only or c.light.name in args.only.split(",")]
    groups: dict = {}
    for c in todo:
        groups.setdefault(c.geometry, []).append(c)
    label = "quick" if args.quick else "full" if design.name == "suite" else design.name
    log(f"hard cases ({label}): {len(todo)} renders x {len(NOISES)} noise levels on {len(groups)} geometries, "
        f"{size} px, {spp} spp, max_depth {args.max_depth}")
    t_start = time.perf_counter()
    rows, render_s = [], 0.0
    for gi, (geo, group) in enumerate(groups.items()):
        mesh = args.out / "meshes" / f"{geo.object}.ply"
        mesh.parent.mkdir(parents=True, exist_ok=True)
        write_ply(mesh, *make_object(geo.object))
        camera = camera_for(geo, size)
        renders = {}
        for c in group:
            renders[c.name] = cached_render(c, mesh, camera, args.out / "renders", spp, args.max_depth)
            render_s += renders[c.name]["seconds"] * (not renders[c.name]["cached"])
            log(f"  [{gi + 1}/{len(groups)}] {geo.key}: {c.name} rendered in {renders[c.name]['seconds']:.1f} s"
                f"{' (cached)' if renders[c.name]['cached'] else ''}, render noise {100 * renders[c.name]['mc']:.2f}%")
        t0 = time.perf_counter()
        root = args.out / "captures" / f"{geo.key}-{size}px-{spp}spp"
        got = run_capture(root, geo, group, renders, camera, tuple(args.sets))
        for r in got:
            c = next(c for c in group if c.name == r["case"])
            r.update({"family": c.light.family, "lighting": c.light.name, "rotation_deg": renders[c.name]["rotation"],
                      "object": geo.object, "elevation_deg": geo.elevation_deg, "albedo": geo.albedo_label,
                      "geometry": geo.key})
        rows += got
        ok = [r for r in got if r["status"] == "ok"]
        log(f"  [{gi + 1}/{len(groups)}] {geo.key}: objcam in {time.perf_counter() - t0:.0f} s; "
            + ", ".join(f"{r['target']} SSIM {r['ssim']:.2f} (row-mean {r['baselines']['row_mean']['ssim']:.2f})"
                        for r in ok) + (f"; {len(got) - len(ok)} not solved" if len(got) > len(ok) else ""))
    wall = time.perf_counter() - t_start
    made_by = invocation("bench.hard", argv)
    header = header_lines(label, len(todo), len(groups), len(rows), size, spp, args.max_depth, wall, render_s,
                          made_by)
    text = markdown(rows, header, NOISES)
    print(text)
    data = json.dumps({"label": label, "size": size, "spp": spp, "max_depth": args.max_depth, "wall_seconds": wall,
                       "render_seconds": render_s, "made_by": made_by, "rows": rows}, indent=1, default=float)
    tag = "" if not args.sets else "-" + hashlib.sha1(" ".join(args.sets).encode()).hexdigest()[:8]
    (args.out / f"rows_{label}{tag}.json").write_text(data)
    if args.write:
        section, title, suffix = ("hard", TITLE, "_quick" if args.quick else "") if design.name == "suite" else \
            ("hard_held_out", HELD_OUT_TITLE, "_held_out")
        write_section(section, text, title, args.results)
        args.results.with_name(f"hard_rows{suffix}.json").write_text(data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
