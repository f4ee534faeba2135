"""``objcam design OUT [--mesh PATH ...] [--objects bunny,sphere,mask] [--image-size 128] ...``: options are
generated from :class:`DesignParams` (so the two never drift); ``--mesh`` is repeatable."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from objcam.errors import ObjcamError

#: the terminal table's columns (design.json key, short heading); the HTML page shows more
TERMINAL_COLUMNS = (("uncertainty_mean", "mean"), ("uncertainty_worst", "worst"), ("spread", "max/mean"),
                    ("azimuth_cv", "az CV"), ("fraction_resolved", "resolved"), ("uncertainty_zenith", "zenith"),
                    ("uncertainty_horizon", "horizon"), ("effective_rank", "rank"))


def add_design_args(p: argparse.ArgumentParser) -> None:
    from objcam.design.params import DesignParams

    p.add_argument("out", type=Path, help="folder to write the comparison into (created)")
    p.add_argument("--mesh", dest="design_meshes", action="append", default=[], metavar="PATH", type=Path,
                   help="compare this mesh too (PLY, OBJ, STL, OFF; scaled to --size); repeatable")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    for name, field in DesignParams.model_fields.items():
        if name == "meshes":
            continue
        default = field.default
        shown = ",".join(default) if isinstance(default, list) else json.dumps(default)
        p.add_argument(f"--{name.replace('_', '-')}", dest=f"design_{name}", default=None, metavar="VALUE",
                       help=f"{field.description or ''} (default {shown})".strip())


def params_from_args(args: argparse.Namespace):
    """A validated DesignParams from the parsed options; ObjcamError (one line) for a bad value."""
    from pydantic import ValidationError

    from objcam.design.params import DesignParams

    values: dict = {"meshes": list(args.design_meshes)}
    for name in DesignParams.model_fields:
        raw = getattr(args, f"design_{name}", None)
        if raw is None or name == "meshes":
            continue
        if name == "objects":
            values[name] = [s.strip() for s in raw.split(",") if s.strip()]
            continue
        try:
            values[name] = json.loads(raw)
        except json.JSONDecodeError:
            values[name] = raw
    try:
        return DesignParams(**values)
    except ValidationError as e:
        msg = "; ".join(f"--{'.'.join(map(str, err['loc'])).replace('_', '-')}: {err['msg']}" for err in e.errors())
        raise ObjcamError(f"bad design option: {msg}", fix="see `objcam design --help`") from None


def print_table(console, results: dict) -> None:
    """The comparison as a rich table (the numbers of design.json)."""
    from rich import box
    from rich.table import Table

    s = results["setup"]
    t = Table(box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True,
              title="objcam design: per-texel uncertainty over the upper sky (lower is better)",
              caption=f"radiance per unit pixel noise; bound {s['uncertainty_bound']:.4g}, resolved below "
                      f"{s['resolved_below']:.4g}; zenith: elevation >= {results['params']['zenith_deg']:g} deg, "
                      f"horizon: < {results['params']['horizon_deg']:g} deg")
    t.add_column("occluder", no_wrap=True)
    for _, heading in TERMINAL_COLUMNS:
        t.add_column(heading, justify="right", no_wrap=True, min_width=len(heading))
    for name, r in results["objects"].items():
        t.add_row(name, *[_short(r["numbers"].get(k)) for k, _ in TERMINAL_COLUMNS])
    console.print(t)


def _short(v) -> str:
    """Short numbers (the table has to fit an 80-column terminal): no exponents, 3 significant digits."""
    if not isinstance(v, float):
        return str(v)
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def run_design_cmd(args: argparse.Namespace) -> int:
    import os

    from rich.console import Console

    from objcam.design.run import run_design

    params = params_from_args(args)
    if args.quiet:
        os.environ["OBJCAM_QUIET"] = "1"
    console = Console(highlight=False)
    res = run_design(args.out, params, log=None if args.quiet else console.print)
    print_table(console, res.results)
    console.print(f"written: {args.out}/ design.json, comparison.png, index.html, and per occluder "
                  "uncertainty.exr|.png, leverage.exr|.png")
    return 0
