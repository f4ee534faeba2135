"""``objcam params [STAGE]``: every stage parameter with its type, default and description."""

from __future__ import annotations

import argparse

from objcam.errors import ObjcamError


def add_params_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("stage", nargs="?", default=None, help="one stage (default: every stage)")


def run_params(args) -> int:
    from objcam.pipeline import graph
    from objcam.pipeline.params import format_params, stage_params, suggestion

    stages = list(graph.STAGES)
    if args.stage is not None:
        if args.stage not in stages:
            raise ObjcamError(f"no stage {args.stage!r}{suggestion(args.stage, stages)}", None,
                              f"use one of {', '.join(stages)}")
        stages = [args.stage]
    out = []
    for s in stages:
        out.append(f"[{s}]  (--set {s}.NAME=VALUE for one run; [params.{s}] in capture.toml keeps a setting)")
        out.append(format_params(stage_params(s)))
        out.append("")
    print("\n".join(out).rstrip())
    return 0
