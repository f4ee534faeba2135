"""Stage parameters as the user sees them: every one listed (``objcam params``, each stage's ``--help``), typos
answered with a suggestion, and the settings a capture keeps in capture.toml (``[params.<stage>]``) merged under
the one-run ``--set`` overrides.

A parameter's name is ``stage.field`` or, inside a nested model (geometry's ``silhouette``, texture's ``bake``),
``stage.field.subfield``; ``--set`` and capture.toml take the same dotted names.
"""

from __future__ import annotations

import difflib
import tomllib
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from objcam.errors import ObjcamError
from objcam.pipeline import graph

TOML_TABLE = "params"  # capture.toml's [params.<stage>] tables


@dataclass(frozen=True)
class ParamInfo:
    """One parameter a stage accepts: ``name`` dotted within the stage (``silhouette.threshold``)."""

    stage: str
    name: str
    type: str
    default: Any
    description: str

    @property
    def full_name(self) -> str:
        return f"{self.stage}.{self.name}"


def _is_model(annotation: Any) -> bool:
    return isinstance(annotation, type) and issubclass(annotation, BaseModel)


def type_name(annotation: Any) -> str:
    """A short readable type: ``int``, ``float | None``, ``'exact' | 'paper'``, ``list[float]``."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_name(a) for a in args)
    if origin is typing.Annotated:
        return type_name(args[0])
    if origin is not None:
        inner = ", ".join(type_name(a) for a in args if a is not Ellipsis)
        return f"{getattr(origin, '__name__', str(origin))}[{inner}]" if inner else getattr(origin, "__name__", "")
    if annotation is type(None):
        return "None"
    return getattr(annotation, "__name__", str(annotation))


def model_params(stage: str, model: type[BaseModel], prefix: str = "") -> list[ParamInfo]:
    """Every field of ``model``, nested models flattened to dotted names."""
    out: list[ParamInfo] = []
    for name, f in model.model_fields.items():
        if _is_model(f.annotation):
            out.extend(model_params(stage, f.annotation, f"{prefix}{name}."))
            continue
        default = f.get_default(call_default_factory=True)
        out.append(ParamInfo(stage, prefix + name, type_name(f.annotation), default, f.description or ""))
    return out


def stage_params(stage: str) -> list[ParamInfo]:
    return model_params(stage, graph.stage_module(stage).Params)


def all_params() -> list[ParamInfo]:
    return [p for s in graph.STAGES for p in stage_params(s)]


def suggestion(word: str, candidates: list[str]) -> str:
    """`` (did you mean X?)`` for the closest candidate, or ``""``."""
    close = difflib.get_close_matches(word, candidates, n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _fmt_default(v: Any) -> str:
    if isinstance(v, BaseModel):
        return v.model_dump_json()
    if isinstance(v, tuple):
        v = list(v)
    return repr(v) if isinstance(v, str) else str(v).replace("'", '"') if isinstance(v, list | dict) else str(v)


def format_params(params: list[ParamInfo], full: bool = True) -> str:
    """Plain text, one parameter a block: ``name  type = default`` then its description, indented."""
    import textwrap

    lines = []
    for p in params:
        lines.append(f"  {p.full_name if full else p.name}  ({p.type}) = {_fmt_default(p.default)}")
        if p.description:
            lines.extend(textwrap.wrap(p.description, 112, initial_indent="      ", subsequent_indent="      "))
    return "\n".join(lines)


def stage_epilog(stage: str) -> str:
    """The text a stage subcommand's ``--help`` ends with: its parameters ("" for a name the graph lacks)."""
    if stage not in graph.STAGES:
        return ""
    return (f"parameters of stage {stage} (--set {stage}.NAME=VALUE for one run; [params.{stage}] in capture.toml "
            f"to keep a setting):\n" + format_params(stage_params(stage), full=False))


# ---- values: capture.toml and --set -------------------------------------------------------------------------

def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    """{"silhouette.k": 1, "x": 2} -> {"silhouette": {"k": 1}, "x": 2}."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        *parents, leaf = key.split(".")
        d = out
        for p in parents:
            nxt = d.setdefault(p, {})
            if not isinstance(nxt, dict):
                nxt = d[p] = {}
            d = nxt
        d[leaf] = value
    return out


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``, nested tables merged key by key."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def capture_params(capture: Path) -> dict[str, dict[str, Any]]:
    """The ``[params.<stage>]`` tables of CAPTURE/capture.toml (nested as TOML reads them); {} without any, or
    when capture.toml is missing or does not parse (the scene stage reports that, naming the line)."""
    path = Path(capture) / "capture.toml"
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return {}
    table = data.get(TOML_TABLE, {})
    if not isinstance(table, dict):
        raise ObjcamError(f"[{TOML_TABLE}] must hold one table per stage, e.g. [params.solve]", path,
                          'write [params.STAGE] tables, e.g. [params.solve] then method = "paper"')
    for stage, values in table.items():
        if stage not in graph.STAGES:
            raise ObjcamError(f"[params.{stage}]: no stage {stage!r}{suggestion(stage, list(graph.STAGES))}", path,
                              f"use one of {', '.join(graph.STAGES)} (objcam params lists every parameter)")
        if not isinstance(values, dict):
            raise ObjcamError(f"params.{stage} must be a table of parameters", path,
                              f"write [params.{stage}] and one NAME = VALUE per line")
    return table


def combined(capture_table: dict[str, dict[str, Any]], overrides: dict[str, dict[str, Any]]) -> dict[str, dict]:
    """capture.toml's settings with ``--set`` (flat dotted names per stage) on top, nested per stage."""
    stages = set(capture_table) | set(overrides)
    return {s: merge(capture_table.get(s, {}), _nest(overrides.get(s, {}))) for s in stages}


def make_params(name: str, values: dict[str, Any] | None, source: Path | None = None) -> BaseModel:
    """Stage ``name``'s Params from ``values`` (nested dict); a bad value or an unknown name is one line, with the
    closest parameter's name when it looks like a typo. ``source``: capture.toml, named when it holds a setting."""
    Params = graph.stage_module(name).Params
    try:
        return Params(**_nest(values or {}))
    except ValidationError as e:
        known = [p.name for p in model_params(name, Params)]
        msgs = []
        for err in e.errors():
            loc = ".".join(map(str, err["loc"]))
            if err["type"] == "extra_forbidden":
                msgs.append(f"unknown parameter {name}.{loc}{suggestion(loc, known)}".replace(
                    "(did you mean ", f"(did you mean {name}."))
            else:
                msgs.append(f"{name}.{loc}: {err['msg']}")
        what = (f"bad setting for stage {name} (--set or [params.{name}] in capture.toml)" if source is not None
                else f"bad --set for stage {name}")
        raise ObjcamError(f"{what}: {'; '.join(msgs)}", source, f"objcam params {name} lists its parameters") from None


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def changes(stage: str, old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """``stage.name old -> new`` for every parameter whose value differs between two ``model_dump(mode="json")``."""
    a, b = _flat(old), _flat(new)
    return [f"{stage}.{k} {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
