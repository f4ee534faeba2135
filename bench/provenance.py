"""Where a bench row's stage time came from (issue 28): this run, or an earlier one found in the cache.

A stage the pipeline skips as unchanged keeps the ``stage.json`` of the run that built it, so a bench that reads
``wall_seconds`` from it after a rerun would report an earlier run's time (on another day's machine, under
another load) as its own. :func:`stage_time` reads the record with its ``finished`` time and says whether the
stage ran after ``since`` (this run) or not (cached); tables flag the cached ones.
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path


def stage_time(work: Path, stage: str, since: float) -> dict:
    """{"seconds", "load", "finished", "cached"} of ``work/stage/stage.json``; ``cached`` is True when the stage
    finished before ``since`` (a ``time.time()`` taken before the run), i.e. this run found it in the cache.
    Seconds before ``since`` by up to 1 s count as this run (the record's time is rounded to the second)."""
    rec = json.loads((Path(work) / stage / "stage.json").read_text())
    finished = _dt.datetime.fromisoformat(rec["finished"]).timestamp()
    return {"seconds": rec.get("wall_seconds"), "load": rec.get("load_average"), "finished": rec["finished"],
            "cached": finished < since - 1.0}


def seconds_cell(seconds: float | None, cached: bool, fmt: str = "{:.1f}") -> str:
    """A table cell for a stage time: the number, marked ``(cached)`` when it is an earlier run's."""
    if seconds is None:
        return ""
    return fmt.format(seconds) + (" (cached)" if cached else "")
