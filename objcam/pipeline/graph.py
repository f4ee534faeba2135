"""The stage graph: which stages exist, in which order, and what each depends on.

A stage module declares ``DEPS`` (stages it needs) and may declare ``OPTIONAL_DEPS`` (stages whose artifacts it
uses when they apply to the capture) and ``applies(capture) -> bool`` with ``APPLIES_WHEN`` (a phrase for
messages): the photo stages (ingest, sfm, geometry, texture, probe) apply only to captures made of photos, and a
known-geometry capture runs scene -> transport -> ... alone. A stage applies when its own test passes and every
stage in its DEPS applies.
"""

from __future__ import annotations

import importlib
from functools import lru_cache
from pathlib import Path
from types import ModuleType

# Topological order. Each name is a module in objcam.stages.
STAGES: tuple[str, ...] = ("ingest", "sfm", "geometry", "texture", "probe",
                           "scene", "transport", "solve", "evaluate", "analysis", "report")
PACKAGE = "objcam.stages"  # tests point this at a package of toy stages


@lru_cache(maxsize=None)
def stage_module(name: str) -> ModuleType:
    if name not in STAGES:
        raise KeyError(name)
    mod = importlib.import_module(f"{PACKAGE}.{name}")
    for attr in ("NAME", "DEPS", "VERSION", "Params", "run"):
        if not hasattr(mod, attr):
            raise TypeError(f"stage module {PACKAGE}.{name} lacks {attr}")
    return mod


def deps(name: str) -> tuple[str, ...]:
    """Required and optional dependencies (the graph's edges)."""
    mod = stage_module(name)
    return tuple(mod.DEPS) + tuple(getattr(mod, "OPTIONAL_DEPS", ()))


def applies(name: str, capture: Path) -> bool:
    """Whether ``name`` has work to do on this capture (its own test, and every required dependency applies)."""
    mod = stage_module(name)
    own = getattr(mod, "applies", None)
    if own is not None and not own(Path(capture)):
        return False
    return all(applies(d, capture) for d in mod.DEPS)


def applies_when(name: str) -> str:
    return getattr(stage_module(name), "APPLIES_WHEN", "always")


def upstream_closure(name: str) -> list[str]:
    """``name`` and every stage it depends on, in run order."""
    need: set[str] = set()

    def visit(n: str) -> None:
        if n in need:
            return
        need.add(n)
        for d in deps(n):
            visit(d)

    visit(name)
    return [s for s in STAGES if s in need]


def downstream_closure(names: set[str]) -> set[str]:
    """``names`` and every stage that depends on any of them, directly or not."""
    out = set(names)
    if not out:
        return out
    for s in STAGES:
        if any(d in out for d in deps(s)):
            out.add(s)
    return out
