"""``objcam synth``: command-line options generated from objcam.synth.capture.SynthParams (known-geometry
captures) and, with ``--full``, objcam.synth.full.FullSynthParams (photographed captures: raw views, brackets,
chrome ball), so the options and the models never drift. An option both models have is one flag; one that only
the other flavour has is refused with a message."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from objcam.errors import ObjcamError


def _models():
    from objcam.synth.capture import SynthParams
    from objcam.synth.full import FullSynthParams

    return SynthParams, FullSynthParams


def add_synth_args(p: argparse.ArgumentParser) -> None:
    SynthParams, FullSynthParams = _models()
    p.add_argument("out", type=Path, help="folder to write the capture into (must not exist or be empty)")
    p.add_argument("--full", action="store_true", help="a photographed capture: raw (DNG) ring of views on the "
                   "printed board, bracketed targets and a chrome ball, cameras left to sfm (objcam.synth.full)")
    seen: set[str] = set()
    for model, tag in ((SynthParams, ""), (FullSynthParams, "[--full] ")):
        for name, field in model.model_fields.items():
            if name in seen:
                continue
            seen.add(name)
            both = name in SynthParams.model_fields and name in FullSynthParams.model_fields
            default = field.default
            shown = json.dumps(default) if default is not None and not callable(default) and \
                isinstance(default, (str, int, float, bool, list, tuple)) else "see the model"
            if both and SynthParams.model_fields[name].default != FullSynthParams.model_fields[name].default:
                shown += f"; with --full {json.dumps(FullSynthParams.model_fields[name].default)}"
            p.add_argument(f"--{name.replace('_', '-')}", dest=f"synth_{name}", default=None, metavar="VALUE",
                           help=f"{'' if both else tag}{field.description or ''} (default {shown})".strip())


def run_synth(args: argparse.Namespace) -> int:
    from pydantic import ValidationError
    from rich.console import Console

    SynthParams, FullSynthParams = _models()
    model = FullSynthParams if getattr(args, "full", False) else SynthParams
    other = SynthParams if model is FullSynthParams else FullSynthParams
    values = {}
    for name in set(SynthParams.model_fields) | set(FullSynthParams.model_fields):
        raw = getattr(args, f"synth_{name}", None)
        if raw is None:
            continue
        if name not in model.model_fields:
            flavour = "with --full" if other is FullSynthParams else "without --full"
            raise ObjcamError(f"bad synth option: --{name.replace('_', '-')} only applies {flavour}")
        try:
            values[name] = json.loads(raw)
        except json.JSONDecodeError:
            values[name] = raw
    try:
        params = model(**values)
    except ValidationError as e:
        msg = "; ".join(f"--{'.'.join(map(str, err['loc'])).replace('_', '-')}: {err['msg']}" for err in e.errors())
        raise ObjcamError(f"bad synth option: {msg}") from None
    if model is FullSynthParams:
        from objcam.synth.full import synthesize_full

        summary = synthesize_full(args.out, params)
    else:
        from objcam.synth.capture import synthesize

        summary = synthesize(args.out, params)
    Console().print(f"synthetic capture written to {args.out}")
    if summary:
        Console().print_json(json.dumps(summary, default=str))
    return 0
