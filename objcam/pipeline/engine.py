"""Runs stages: resolves params, computes cache keys, skips what is unchanged, runs the rest into a temporary
folder and renames it into place, under a lock on the work folder."""

from __future__ import annotations

import datetime as _dt
import errno
import fcntl
import json
import math
import os
import shutil
import stat
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
from objcam.heap import reuse_freed_memory
from objcam.image_io import atomic_write_text
from objcam.pipeline import graph
from objcam.pipeline import integrity, workdir
from objcam.pipeline.cache import code_digest, file_digest, manifest_digest, stage_key
from objcam.pipeline.inputs import check_input
from objcam.pipeline.params import capture_params, changes, combined, make_params, suggestion
from objcam.pipeline.stage import StageInputs
from objcam.schemas.stage_record import StageRecord

HASH_MEMO = ".hashes.json"
LOCK = workdir.LOCK


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
            raise ObjcamError(f"--set {item!r}: no stage {stage!r}{suggestion(stage, list(graph.STAGES))} "
                              f"(stages: {', '.join(graph.STAGES)})")
        try:
            parsed: Any = json.loads(value)
        except json.JSONDecodeError:
            parsed = value
        if _non_finite(parsed):  # json.loads reads NaN, Infinity: never a meaningful setting
            raise ObjcamError(f"--set {item!r}: the value is not a finite number", None,
                              "give a finite number (see the stage's params)")
        out.setdefault(stage, {})[param] = parsed
    return out


def _regular(path: Path) -> bool:
    """True when ``path`` itself (not followed) is a regular file."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def _non_finite(value: Any) -> bool:
    if isinstance(value, float):
        return not math.isfinite(value)
    if isinstance(value, list):
        return any(_non_finite(v) for v in value)
    if isinstance(value, dict):
        return any(_non_finite(v) for v in value.values())
    return False


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
                 overrides: dict[str, dict[str, Any]] | None = None, quiet: bool = False,
                 allow_outside_inputs: bool = False):
        self.capture = Path(capture).resolve()
        if not self.capture.is_dir():
            raise ObjcamError("capture folder not found", self.capture, "give the folder that holds capture.toml")
        # never resolve the work folder: a symbolic link there is refused, not followed (workdir.refuse_links)
        self.work = workdir.absolute(work) if work else default_work_dir(self.capture)
        self.explicit_work = work is not None
        self.allow_outside_inputs = allow_outside_inputs
        # capture.toml's [params.<stage>] settings, with the one-run --set overrides on top
        self.cli_overrides = overrides or {}
        self.kept = capture_params(self.capture)
        self.overrides = combined(self.kept, self.cli_overrides)
        self.quiet = quiet
        self._memo: dict[str, list] = {}
        self._keys: dict[str, str] = {}
        self._applies: dict[str, bool] = {}

    # ---- keys -------------------------------------------------------------------------------------
    def stage_dir(self, name: str) -> Path:
        return self.work / name

    def params(self, name: str) -> BaseModel:
        toml = self.capture / "capture.toml" if name in self.kept else None
        return make_params(name, self.overrides.get(name), toml)

    def changed_params(self, name: str, rec: StageRecord | None) -> list[str]:
        """``stage.param old -> new`` for each parameter the last run of ``name`` used differently."""
        if rec is None or not isinstance(rec.params, dict):
            return []
        return changes(name, rec.params, self.params(name).model_dump(mode="json"))

    def _inputs(self, name: str) -> dict[str, str]:
        mod = graph.stage_module(name)
        files = mod.input_files(self.capture) if hasattr(mod, "input_files") else []
        out = {}
        outside_ok = self.allow_outside_inputs or getattr(mod, "READS_OUTSIDE_CAPTURE", False)
        for f in files:
            f = Path(f)
            rel = os.path.relpath(f, self.capture)
            if rel.startswith("..") and getattr(mod, "READS_OUTSIDE_CAPTURE", False):
                rel = f"outside:{f.name}"  # by name and content: a copied or moved capture keeps its key
            if not check_input(f, self.capture, outside_ok):
                out[rel] = "missing"
            elif rel == "capture.toml":
                out[rel] = manifest_digest(f)
            else:
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
        if self.stage_dir(name).is_symlink() or not _regular(p):
            return None  # a link, FIFO or device planted in a capture's objcam/ would lead elsewhere or hang
        try:
            return StageRecord.model_validate_json(p.read_text())
        except (OSError, ValidationError, ValueError):
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
            elif rec.key == key and integrity.damage(self.stage_dir(name), rec.artifacts, self._memo) is not None:
                state = "damaged"
            elif rec.key == key:
                state = "done"
            else:
                state = "stale"
            changed = self.changed_params(name, rec) if state == "stale" else []
            rows.append({"stage": name, "state": state, "seconds": rec.wall_seconds if rec else None,
                         "key": rec.key if rec else "", "current_key": key, "changed": changed,
                         "summary": rec.summary if rec else "", "finished": rec.finished if rec else ""})
        return rows

    # ---- running ----------------------------------------------------------------------------------
    @contextmanager
    def lock(self) -> Iterator[None]:
        workdir.prepare(self.work, self.explicit_work)
        fd = workdir.open_lock(self.work)
        try:
            if not workdir.try_lock(fd):
                holder = workdir.read_holder(fd) or "another process"
                raise ObjcamError(f"another objcam run holds the lock ({holder})", self.work,
                                  "wait for it to finish (the lock is freed when that process exits)")
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()}".encode())
            self._clean_leftovers()
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def _clean_leftovers(self) -> None:
        """Remove temporary folders a killed run left behind (never a finished stage)."""
        for p in list(self.work.glob(".tmp-*")) + list(self.work.glob(".old-*")):
            if p.is_symlink() or not p.is_dir():
                p.unlink(missing_ok=True)  # never delete through a link
            else:
                shutil.rmtree(p, ignore_errors=True)

    def _load_memo(self) -> None:
        try:
            memo = json.loads((self.work / HASH_MEMO).read_text()) if _regular(self.work / HASH_MEMO) else {}
        except (OSError, ValueError):
            memo = {}
        self._memo = memo if isinstance(memo, dict) else {}

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
        changed = self.changed_params(name, rec) if rec is not None and rec.key != key else []
        # never silently: a rerun that undoes a setting of the last run says which (keep one in capture.toml)
        note = f"params changed since the last run: {'; '.join(changed)}; " if changed else ""
        if rec is not None and rec.key == key and not forced:
            damage = integrity.damage(self.stage_dir(name), rec.artifacts, self._memo)
            if damage is None:
                return StageReport(name, "cached", key, rec.wall_seconds, rec.summary, rec.metrics)
            note = f"rebuilt: cached artifacts damaged ({damage}); "

        tmp = self.work / f".tmp-{name}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir(parents=True)
        upstream = {d: self.stage_dir(d) for d in self.upstream_of(name)}
        inputs = StageInputs(capture=self.capture, upstream=upstream, out=tmp, quiet=self.quiet)
        load = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
        t0 = time.perf_counter()
        try:
            with _PeakRSS() as mem, reuse_freed_memory():  # no page faults for each large temporary array
                outputs = mod.run(inputs, parts["params"])
        except ObjcamError:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        except KeyboardInterrupt:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        except OSError as e:
            shutil.rmtree(tmp, ignore_errors=True)
            if e.errno in (errno.ENOSPC, errno.EDQUOT):
                raise ObjcamError(f"stage {name}: the disk is full ({e.strerror})", self.work,
                                  "free some space, or give --work DIR on a disk with room") from None
            if e.errno in (errno.EROFS, errno.EACCES) and Path(getattr(e, "filename", "") or "/").is_relative_to(self.work):
                raise ObjcamError(f"stage {name}: cannot write its artifacts ({e.strerror})", self.work,
                                  "give a writable artifact folder with --work DIR") from None
            self._internal_error(name, tmp, e)
        except Exception as e:
            self._internal_error(name, tmp, e)
        seconds = time.perf_counter() - t0
        artifacts = integrity.record_artifacts(tmp)
        record = StageRecord(
            stage=name, key=key, code=parts["code"], params=parts["params"].model_dump(mode="json"),
            inputs=parts["inputs"], upstream=parts["upstream"], wall_seconds=round(seconds, 3),
            peak_rss_mb=round(mem.peak / 2**20, 1), load_average=load, metrics=outputs.metrics, summary=outputs.summary,
            finished=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), objcam_version=__version__,
            artifacts=artifacts,
        )
        atomic_write_text(tmp / "stage.json", record.model_dump_json(indent=2))
        self._install(tmp, self.stage_dir(name))
        integrity.remember(self.stage_dir(name), artifacts, self._memo)
        (self.work / f"{name}.error.log").unlink(missing_ok=True)
        return StageReport(name, "ran", key, seconds, note + outputs.summary, outputs.metrics)

    def _internal_error(self, name: str, tmp: Path, e: BaseException) -> None:
        """An unexpected failure: the traceback goes to a log file, the user gets one line pointing at it."""
        shutil.rmtree(tmp, ignore_errors=True)
        log = self.work / f"{name}.error.log"
        atomic_write_text(log, traceback.format_exc())
        raise StageError(f"stage {name} failed: {type(e).__name__}: {e}", log,
                         "the traceback is in this file; please report it") from None

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
