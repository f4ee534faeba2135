"""Progress bars for long work (tqdm on stderr), silenced in quiet mode or when OBJCAM_QUIET=1."""

from __future__ import annotations

import os
from typing import Iterable, TypeVar

T = TypeVar("T")


def quiet() -> bool:
    return os.environ.get("OBJCAM_QUIET", "") not in ("", "0")


def bar(iterable: Iterable[T] | None = None, total: int | None = None, desc: str = "", unit: str = "it"):
    """A tqdm bar (use as an iterable wrapper or with .update(n)); disabled when quiet."""
    from tqdm.auto import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=quiet(), leave=False, dynamic_ncols=True)
