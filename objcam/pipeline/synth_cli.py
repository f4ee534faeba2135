"""``objcam synth``: command-line options generated from objcam.synth.SynthParams, so the two never drift."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from objcam.errors import ObjcamError


def add_synth_args(p: argparse.ArgumentParser) -> None:
    from objcam.synth import SynthParams

    p.add_argument("out", type=Path, help="folder to write the capture into (must not exist or be empty)")
    for name, field in SynthParams.model_fields.items():
        default = field.default
        shown = json.dumps(default) if default is not None and not callable(default) else "none"
        p.add_argument(f"--{name.replace('_', '-')}", dest=f"synth_{name}", default=None, metavar="VALUE",
                       help=f"{field.description or ''} (default {shown})".strip())


def run_synth(args: argparse.Namespace) -> int:
    from pydantic import ValidationError
    from rich.console import Console

    from objcam.synth import SynthParams, synthesize

    values = {}
    for name in SynthParams.model_fields:
        raw = getattr(args, f"synth_{name}")
        if raw is None:
            continue
        try:
            values[name] = json.loads(raw)
        except json.JSONDecodeError:
            values[name] = raw
    try:
        params = SynthParams(**values)
    except ValidationError as e:
        msg = "; ".join(f"--{'.'.join(map(str, err['loc'])).replace('_', '-')}: {err['msg']}" for err in e.errors())
        raise ObjcamError(f"bad synth option: {msg}") from None
    summary = synthesize(args.out, params)
    Console().print(f"synthetic capture written to {args.out}")
    if summary:
        Console().print_json(json.dumps(summary, default=str))
    return 0
