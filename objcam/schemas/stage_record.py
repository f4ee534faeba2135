"""``stage.json``: what the engine records beside every finished stage's artifacts."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict


class StageRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")
    stage: str
    key: str  # hash of everything below that determines the outputs
    code: str  # hash of the stage's source
    params: dict[str, Any]
    inputs: dict[str, str]  # capture file (relative path) -> sha256
    upstream: dict[str, str]  # upstream stage -> its key
    wall_seconds: float
    peak_rss_mb: float  # peak resident memory of the process while the stage ran
    load_average: float | None = None  # the machine's 1-minute load average when the stage started (timings)
    metrics: dict[str, Any]
    summary: str
    finished: str  # ISO time
    objcam_version: str
    # relative path -> [size in bytes, sha256] of every file the stage wrote (objcam.pipeline.integrity); None in
    # records written before artifacts were recorded (such a stage is rebuilt once)
    artifacts: dict[str, list] | None = None
