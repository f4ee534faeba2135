"""What a stage receives and returns. Stages never choose paths: the engine hands them folders."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class StageInputs:
    """capture: the capture folder (read-only; stages never write into it).
    upstream: name -> finished artifact folder of each stage in DEPS (read-only).
    out: an empty folder for this stage's artifacts; the engine renames it into place when run() returns.
    """

    capture: Path
    upstream: dict[str, Path]
    out: Path
    quiet: bool = False


@dataclass
class StageOutputs:
    """metrics: JSON-able numbers and short strings for stage.json and the summary table.
    summary: one line for the terminal (e.g. "A: 9,812 px x 1,024 texels (direct K=4) in 3.1 s")."""

    metrics: dict[str, Any] = field(default_factory=dict)
    summary: str = ""
