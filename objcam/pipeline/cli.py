"""``objcam`` command line: run the pipeline on a capture, one stage of it, its status, or make a synthetic scene.

    objcam run CAPTURE [--until S] [--force S] [--set stage.param=value] [--work DIR]
    objcam run C1 C2 ... [--cluster local[:N] | tcp://HOST:PORT | NAME]   a batch; transport shards on Dask
    objcam <stage> CAPTURE [...]          run one stage (and what it needs)
    objcam status CAPTURE                 done / stale / missing for every stage
    objcam synth OUT [--object bunny] [--envmap forest] ...
    objcam evaluate CAPTURE               metrics against truth/ (synthetic captures)
    objcam design OUT [--mesh PATH] ...   compare occluders (bunny, sphere, coded mask, meshes); no capture
    objcam params [STAGE]                 every stage parameter: type, default, description
    objcam export CAPTURE OUT             envmaps (EXR, HDR), meshes (PLY, OBJ, GLB), cameras, Mitsuba/Blender scenes
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import sys
from pathlib import Path

from rich.markup import escape

from objcam.errors import ObjcamError, one_line
from objcam.pipeline import graph


def _console():
    from rich.console import Console

    return Console(stderr=False, highlight=False)


def _pipeline_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder (holds capture.toml)")
    p.add_argument("--work", type=Path, default=None, help="artifact folder (default CAPTURE/objcam)")
    p.add_argument("--force", action="append", default=[], metavar="STAGE",
                   help="rerun this stage and everything downstream even if cached (repeatable)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                   help="override a stage parameter for this run, e.g. --set transport.model=direct (repeatable; "
                   "`objcam params` lists them; [params.STAGE] in capture.toml keeps a setting)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.add_argument("--allow-outside-inputs", action="store_true",
                   help="read inputs that lie outside the capture folder (refused by default)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="objcam", description="Turn an ordinary object into a camera.")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run the pipeline (cached stages are skipped)")
    _pipeline_args(p)
    p.add_argument("--until", default=None, metavar="STAGE", help="stop after this stage")
    p.add_argument("more", nargs="*", type=Path, metavar="CAPTURE",
                   help="more captures: run each in turn, one summary table, exit status = captures failed")
    p.add_argument("--cluster", default=None, metavar="SPEC",
                   help="build the transport's column shards on Dask: local[:N], tcp://HOST:PORT or a cluster "
                   "named in Dask's config (objcam.clusters.NAME; README: Slurm)")
    from objcam.pipeline.params import stage_epilog

    for name in graph.STAGES:
        if name == "evaluate":
            continue
        p = sub.add_parser(name, help=f"run stage '{name}' (and any stage it needs)", epilog=stage_epilog(name),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        _pipeline_args(p)
    p = sub.add_parser("evaluate", help="metrics against the capture's truth/ (runs what is needed first)",
                       epilog=stage_epilog("evaluate"), formatter_class=argparse.RawDescriptionHelpFormatter)
    _pipeline_args(p)
    p = sub.add_parser("status", help="which stages are done, stale or missing")
    p.add_argument("capture", type=Path)
    p.add_argument("--work", type=Path, default=None)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.PARAM=VALUE")
    p.add_argument("--allow-outside-inputs", action="store_true")
    p = sub.add_parser("synth", help="render a synthetic known-geometry capture")
    from objcam.pipeline.synth_cli import add_synth_args

    add_synth_args(p)
    p = sub.add_parser("design", help="compare object-cameras (occluders) on one setup; no capture needed")
    from objcam.design.cli import add_design_args

    add_design_args(p)
    p = sub.add_parser("params", help="list every stage parameter (type, default, description)")
    from objcam.pipeline.params_cli import add_params_args

    add_params_args(p)
    p = sub.add_parser("export", help="envmaps, meshes, cameras, Mitsuba and Blender scenes for other tools")
    from objcam.pipeline.export_cli import add_export_args

    add_export_args(p)
    return ap


def _print_reports(console, reports, title: str) -> None:
    from rich.table import Table

    t = Table(title=title, show_lines=False)
    for col in ("stage", "status", "time", "summary"):
        t.add_column(col, overflow="fold")
    for r in reports:
        style = {"ran": "green", "cached": "cyan", "failed": "red", "n/a": "dim"}.get(r.status, "")
        t.add_row(r.stage, f"[{style}]{r.status}[/]", f"{r.seconds:.2f} s", escape(r.summary))
    console.print(t)


def _run_until(args) -> int:
    """``objcam run`` of one capture (module-level: a batch sends it to the captures' processes)."""
    return _run(args, until=args.until)


def _run(args, only: list[str] | None = None, until: str | None = None) -> int:
    from objcam.pipeline.engine import Pipeline, parse_overrides

    console = _console()
    if args.quiet:
        os.environ["OBJCAM_QUIET"] = "1"
    pipe = Pipeline(args.capture, args.work, parse_overrides(args.overrides), quiet=args.quiet,
                    allow_outside_inputs=args.allow_outside_inputs)

    def live(rep) -> None:
        if rep.status == "n/a":
            return  # a photo stage on a known-geometry capture: the summary table lists it
        word = "skipped (unchanged)" if rep.status == "cached" else f"done in {rep.seconds:.2f} s"
        console.print(f"[bold]{rep.stage}[/]: {word}  {escape(rep.summary)}")

    reports = pipe.run(until=until, force=args.force, only=only, on_stage=live)
    _print_reports(console, reports, f"objcam: {args.capture}")
    console.print(f"artifacts: {pipe.work}")
    for line in _result_paths(pipe, {r.stage for r in reports if r.status in ("ran", "cached")}):
        console.print(line)
    return 0


def _result_paths(pipe, done: set[str]) -> list[str]:
    """Where the results of this run are: each target's envmap (EXR, standard lat-long) and the report."""
    lines = []
    if "solve" in done:
        for env in sorted(pipe.stage_dir("solve").glob("*/envmap.exr")):
            lines.append(f"envmap {env.parent.name}: {env}{_verdict_note(env.parent / 'solve.json')}")
    page = pipe.stage_dir("report") / "index.html"
    if "report" in done and page.is_file():
        lines.append(f"report: {page}")
    if lines:
        lines.append(f"for Blender, Mitsuba, viewers: objcam export {escape(str(pipe.capture))} OUT")
    return lines


def _verdict_note(solve_json) -> str:
    """' (verdict GRADE: first reason)' from a target's solve.json (objcam.solvers.plan.verdict), '' without."""
    try:
        v = json.loads(solve_json.read_text()).get("verdict") or {}
    except (OSError, ValueError):
        return ""
    if not v.get("grade"):
        return ""
    style = {"green": "green", "yellow": "yellow", "red": "bold red"}.get(v["grade"], "")
    why = f": {escape(v['reasons'][0])}" if v.get("reasons") else ""
    return f"  [{style}]verdict {v['grade']}[/]{why}"


def _status(args) -> int:
    from rich.table import Table

    from objcam.pipeline.engine import Pipeline, parse_overrides

    pipe = Pipeline(args.capture, args.work, parse_overrides(args.overrides),
                    allow_outside_inputs=args.allow_outside_inputs)
    t = Table(title=f"objcam status: {args.capture}")
    for col in ("stage", "state", "time", "key", "summary"):
        t.add_column(col, overflow="fold")
    for row in pipe.status():
        style = {"done": "green", "stale": "yellow", "damaged": "yellow", "missing": "red", "n/a": "dim"}[row["state"]]
        secs = f"{row['seconds']:.2f} s" if row["seconds"] is not None else ""
        summary = row["summary"]
        if row.get("changed"):  # compared against capture.toml's [params] (and this call's --set)
            summary = f"params differ from the last run: {'; '.join(row['changed'])}"
        t.add_row(row["stage"], f"[{style}]{row['state']}[/]", secs, row["key"], escape(summary))
    _console().print(t)
    return 0


def _evaluate(args) -> int:
    _run(args, only=["evaluate"])
    from objcam.pipeline.engine import Pipeline

    pipe = Pipeline(args.capture, args.work, allow_outside_inputs=args.allow_outside_inputs)
    metrics = json.loads((pipe.stage_dir("evaluate") / "metrics.json").read_text())
    _console().print_json(json.dumps(metrics))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "run" and (args.more or args.cluster):
            from objcam.pipeline.batch import run_batch  # several captures, or a Dask cluster

            return run_batch(args, _run_until)
        if args.command == "run":
            return _run(args, until=args.until)
        if args.command == "status":
            return _status(args)
        if args.command == "evaluate":
            return _evaluate(args)
        if args.command == "synth":
            from objcam.pipeline.synth_cli import run_synth

            return run_synth(args)
        if args.command == "design":
            from objcam.design.cli import run_design_cmd

            return run_design_cmd(args)
        if args.command == "export":
            from objcam.pipeline.export_cli import run_export

            return run_export(args)
        if args.command == "params":
            from objcam.pipeline.params_cli import run_params

            return run_params(args)
        return _run(args, only=[args.command])
    except ObjcamError as e:
        print(f"objcam: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the disk, not objcam: full, read-only, no permission
        if e.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM):
            raise
        where = f"{e.filename}: " if e.filename else ""
        fix = "free some space or give --work DIR elsewhere" if e.errno in (errno.ENOSPC, errno.EDQUOT) else \
            "give a writable artifact folder with --work DIR"
        print(one_line(f"objcam: error: {where}{e.strerror} -- fix: {fix}"), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("objcam: interrupted; finished stages are kept, rerun to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
