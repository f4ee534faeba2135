"""Runs stages: resolves params, computes cache keys, skips what is unchanged, runs the rest into a temporary
folder and renames it into place, under a lock on the work folder."""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import shutil
import threading
import time
import traceback
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from pydantic import BaseModel, ValidationError

from objcam import __version__
from objcam.errors import ObjcamError, StageError
from objcam.image_io import atomic_write_text
from objcam.pipeline import graph
from objcam.pipeline.cache import code_digest, file_digest, stage_key
from objcam.pipeline.stage import StageInputs
from objcam.schemas.stage_record import StageRecord

HASH_MEMO = ".hashes.json"
LOCK = ".lock"


def default_work_dir(capture: Path) -> Path:
    return Path(capture) / "objcam"


def parse_overrides(items: list[str]) -> dict[str, dict[str, Any]]:
    """``["transport.samples=4", "solve.method=paper"]`` -> {"transport": {"samples": 4}, "solve": {"method": "paper"}}.
    Values are read as JSON when they parse (numbers, true/false, lists), else as strings."""
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ObjcamError(f"--set {item!r}: expected stage.param=value (e.g. transport.samples=4)")
        lhs, value = item.split("=", 1)
        stage, param = lhs.split(".", 1)
        if stage not in graph.STAGES:
            raise ObjcamError(f"--set {item!r}: no stage {stage!r} (stages: {', '.join(graph.STAGES)})")
        try:
            parsed: Any = json.loads(value)
        except json.JSONDecodeError:
            parsed = value
        out.setdefault(stage, {})[param] = parsed
    return out


def make_params(name: str, overrides: dict[str, Any] | None) -> BaseModel:
    Params = graph.stage_module(name).Params
    try:
        return Params(**(overrides or {}))
    except ValidationError as e:
        msg = "; ".join(f"{name}.{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())
        fields = ", ".join(Params.model_fields)
        raise ObjcamError(f"bad --set for stage {name}: {msg} (params: {fields})") from None


@dataclass
class StageReport:
    stage: str
    status: str  # "ran", "cached", "failed", "n/a" (the stage does not apply to this capture)
    key: str
    seconds: float = 0.0
    summary: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)


class _PeakRSS:
    """Samples the process's resident memory in a thread while a stage runs (ru_maxrss only ever grows)."""

    def __init__(self, interval: float = 0.05):
        self.interval, self.peak, self._stop = interval, 0, threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    @staticmethod
    def _rss() -> int:
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:
            return 0

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            self._stop.wait(self.interval)

    def __enter__(self) -> "_PeakRSS":
        self.peak = self._rss()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._rss())


class Pipeline:
    """One capture's pipeline. ``work`` defaults to CAPTURE/objcam."""

    def __init__(self, capture: str | Path, work: str | Path | None = None,
                 overrides: dict[str, dict[str, Any]] | None = None, quiet: bool = False):
        self.capture = Path(capture).resolve()
        if not self.capture.is_dir():
            raise ObjcamError("capture folder not found", self.capture, "give the folder that holds capture.toml")
        self.work = Path(work).resolve() if work else default_work_dir(self.capture)
        self.overrides = overrides or {}
        self.quiet = quiet
        self._memo: dict[str, list] = {}
        self._keys: dict[str, str] = {}
        self._applies: dict[str, bool] = {}

    # ---- keys -------------------------------------------------------------------------------------
    def stage_dir(self, name: str) -> Path:
        return self.work / name

    def params(self, name: str) -> BaseModel:
        return make_params(name, self.overrides.get(name))

    def _inputs(self, name: str) -> dict[str, str]:
        mod = graph.stage_module(name)
        files = mod.input_files(self.capture) if hasattr(mod, "input_files") else []
        out = {}
        for f in files:
            f = Path(f)
            rel = os.path.relpath(f, self.capture)
            out[rel] = file_digest(f, self._memo)
        return out

    def applies(self, name: str) -> bool:
        if name not in self._applies:
            self._applies[name] = graph.applies(name, self.capture)
        return self._applies[name]

    def upstream_of(self, name: str) -> list[str]:
        """The dependencies whose artifacts ``name`` reads on this capture (optional ones only where they apply)."""
        mod = graph.stage_module(name)
        return list(mod.DEPS) + [d for d in getattr(mod, "OPTIONAL_DEPS", ()) if self.applies(d)]

    def key(self, name: str) -> tuple[str, dict]:
        """The key a run of ``name`` would have now, and the parts it hashes."""
        mod = graph.stage_module(name)
        params = self.params(name)
        inputs = self._inputs(name)
        upstream = {d: self.key(d)[0] for d in self.upstream_of(name)}
        code = code_digest(mod)
        key = stage_key(name, code, params, inputs, upstream)
        self._keys[name] = key
        return key, {"params": params, "inputs": inputs, "upstream": upstream, "code": code}

    def record(self, name: str) -> StageRecord | None:
        p = self.stage_dir(name) / "stage.json"
        try:
            return StageRecord.model_validate_json(p.read_text())
        except (FileNotFoundError, ValidationError, ValueError):
            return None

    def status(self) -> list[dict[str, Any]]:
        """One row per stage: done / stale / missing, its time and keys."""
        rows = []
        for name in graph.STAGES:
            rec = self.record(name)
            if not self.applies(name):
                rows.append({"stage": name, "state": "n/a", "seconds": None, "key": "", "current_key": "",
                             "summary": f"applies when {graph.applies_when(name)}", "finished": ""})
                continue
            try:
                key = self.key(name)[0]
            except ObjcamError as e:
                key = f"error: {e}"
            if rec is None:
                state = "missing"
            elif rec.key == key:
                state = "done"
            else:
                state = "stale"
            rows.append({"stage": name, "state": state, "seconds": rec.wall_seconds if rec else None,
                         "key": rec.key if rec else "", "current_key": key,
                         "summary": rec.summary if rec else "", "finished": rec.finished if rec else ""})
        return rows

    # ---- running ----------------------------------------------------------------------------------
    @contextmanager
    def lock(self) -> Iterator[None]:
        self.work.mkdir(parents=True, exist_ok=True)
        path = self.work / LOCK
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = Path(path).read_text().strip() or "another process"
                raise ObjcamError(f"another objcam run holds the lock ({holder})", self.work,
                                  "wait for it to finish (the lock is freed when that process exits)") from None
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()}".encode())
            self._clean_leftovers()
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def _clean_leftovers(self) -> None:
        """Remove temporary folders a killed run left behind (never a finished stage)."""
        for p in self.work.glob(".tmp-*"):
            shutil.rmtree(p, ignore_errors=True)
        for p in self.work.glob(".old-*"):
            shutil.rmtree(p, ignore_errors=True)

    def _load_memo(self) -> None:
        try:
            self._memo = json.loads((self.work / HASH_MEMO).read_text())
        except (FileNotFoundError, ValueError):
            self._memo = {}

    def _save_memo(self) -> None:
        atomic_write_text(self.work / HASH_MEMO, json.dumps(self._memo))

    def plan(self, until: str | None = None, only: list[str] | None = None) -> list[str]:
        if only:
            need: set[str] = set()
            for s in only:
                need.update(graph.upstream_closure(s))
            return [s for s in graph.STAGES if s in need]
        if until is None:
            return list(graph.STAGES)
        if until not in graph.STAGES:
            raise ObjcamError(f"--until {until!r}: no such stage (stages: {', '.join(graph.STAGES)})")
        return graph.upstream_closure(until)

    def run(self, until: str | None = None, force: list[str] | None = None,
            only: list[str] | None = None, on_stage=None) -> list[StageReport]:
        """Run the planned stages in order; return one report per stage. ``on_stage(report)`` is called after
        each (for live output)."""
        for f in force or []:
            if f not in graph.STAGES:
                raise ObjcamError(f"--force {f!r}: no such stage (stages: {', '.join(graph.STAGES)})")
        forced = graph.downstream_closure(set(force or []))
        plan = self.plan(until, only)
        for name in only or []:
            if not self.applies(name):
                raise ObjcamError(f"stage {name} does not apply to this capture: it runs when "
                                  f"{graph.applies_when(name)}", self.capture / "capture.toml")
        for name in plan:  # a bad --set fails before any stage runs, not after the slow ones
            self.params(name)
        reports: list[StageReport] = []
        with self.lock():
            self._load_memo()
            try:
                for name in plan:
                    rep = self._run_one(name, name in forced)
                    reports.append(rep)
                    if on_stage:
                        on_stage(rep)
            finally:
                self._save_memo()
        return reports

    def _run_one(self, name: str, forced: bool) -> StageReport:
        mod = graph.stage_module(name)
        if not self.applies(name):
            return StageReport(name, "n/a", "", 0.0, f"not needed (runs when {graph.applies_when(name)})")
        key, parts = self.key(name)
        rec = self.record(name)
        if rec is not None and rec.key == key and not forced:
            return StageReport(name, "cached", key, rec.wall_seconds, rec.summary, rec.metrics)

        tmp = self.work / f".tmp-{name}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir(parents=True)
        upstream = {d: self.stage_dir(d) for d in self.upstream_of(name)}
        inputs = StageInputs(capture=self.capture, upstream=upstream, out=tmp, quiet=self.quiet)
        load = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
        t0 = time.perf_counter()
        try:
            with _PeakRSS() as mem:
                outputs = mod.run(inputs, parts["params"])
        except ObjcamError:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        except KeyboardInterrupt:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        except Exception as e:
            shutil.rmtree(tmp, ignore_errors=True)
            log = self.work / f"{name}.error.log"
            atomic_write_text(log, traceback.format_exc())
            raise StageError(f"stage {name} failed: {type(e).__name__}: {e}", log,
                             "the traceback is in this file; please report it") from None
        seconds = time.perf_counter() - t0
        record = StageRecord(
            stage=name, key=key, code=parts["code"], params=parts["params"].model_dump(mode="json"),
            inputs=parts["inputs"], upstream=parts["upstream"], wall_seconds=round(seconds, 3),
            peak_rss_mb=round(mem.peak / 2**20, 1), load_average=load, metrics=outputs.metrics, summary=outputs.summary,
            finished=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), objcam_version=__version__,
        )
        atomic_write_text(tmp / "stage.json", record.model_dump_json(indent=2))
        self._install(tmp, self.stage_dir(name))
        (self.work / f"{name}.error.log").unlink(missing_ok=True)
        return StageReport(name, "ran", key, seconds, outputs.summary, outputs.metrics)

    def _install(self, tmp: Path, final: Path) -> None:
        """Swap a finished temporary folder into place. At every instant ``final`` is either the old complete
        artifact, absent, or the new complete artifact; leftovers are cleaned on the next run."""
        old = None
        if final.exists():
            old = final.parent / f".old-{final.name}-{uuid.uuid4().hex[:8]}"
            os.replace(final, old)
        os.replace(tmp, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
