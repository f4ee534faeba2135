"""The stage graph: which stages exist, in which order, and what each depends on."""

from __future__ import annotations

import importlib
from functools import lru_cache
from types import ModuleType

# Topological order. Each name is a module in objcam.stages.
STAGES: tuple[str, ...] = ("scene", "transport", "solve", "evaluate", "analysis", "report")
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
    return tuple(stage_module(name).DEPS)


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
