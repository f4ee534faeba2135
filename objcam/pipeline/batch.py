"""``objcam run C1 C2 ... [--cluster SPEC]``: many captures, each capture's stages in order, on one cluster.

The captures run one after another in this process (their stages' own work as always); with ``--cluster`` the
transport's column shards of every capture go to the one cluster (objcam.pipeline.cluster,
objcam.transport.shards). A capture that fails is reported and the next one runs; one summary table at the end;
the exit status is the number of captures that failed. One capture without ``--cluster`` never comes here (the
plain in-process run, with no Dask import).
"""

from __future__ import annotations

import argparse
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass

from objcam.errors import ObjcamError, one_line


@dataclass
class CaptureResult:
    capture: str
    status: str  # done | failed
    seconds: float
    note: str  # the error, or where the results are


def run_batch(args: argparse.Namespace, run_one) -> int:
    """Run ``run_one(args_for_one_capture)`` per capture (args.capture plus args.more) under args.cluster's
    engine. One capture: as a plain run (its error raised); several: a summary table, exit status = failures."""
    captures = [args.capture, *getattr(args, "more", [])]
    if len(captures) > 1 and args.work is not None:
        raise ObjcamError("--work names one artifact folder and this run has several captures",
                          fix="drop --work (each capture keeps its artifacts in CAPTURE/objcam)")
    if len(set(map(str, captures))) != len(captures):
        raise ObjcamError("a capture is named twice in this run", fix="name each capture once")
    with _engine(args.cluster) as engine_note:
        if len(captures) == 1:
            return run_one(args)
        results = []
        for cap in captures:
            one = argparse.Namespace(**(vars(args) | {"capture": cap, "more": []}))
            t0 = time.perf_counter()
            try:
                run_one(one)
                results.append(CaptureResult(str(cap), "done", time.perf_counter() - t0, ""))
            except ObjcamError as e:
                print(f"objcam: error: {e}", file=sys.stderr)
                results.append(CaptureResult(str(cap), "failed", time.perf_counter() - t0, str(e)))
            except Exception as e:  # a bug in one capture's run must not stop the others
                msg = one_line(f"{type(e).__name__}: {e}")
                print(f"objcam: error: {cap}: {msg}", file=sys.stderr)
                results.append(CaptureResult(str(cap), "failed", time.perf_counter() - t0, msg))
        _print_summary(results, engine_note)
        return sum(r.status == "failed" for r in results)


@contextmanager
def _engine(spec: str | None):
    """The transport engine for the run: shards on the cluster SPEC, else in-process."""
    if not spec:
        yield "in-process"
        return
    from objcam.pipeline.cluster import connect
    from objcam.transport.engine import using
    from objcam.transport.shards import DaskEngine

    with connect(spec) as client, using(DaskEngine(client)):
        yield f"transport shards on {spec}"


def _print_summary(results: list[CaptureResult], engine_note: str) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    failed = sum(r.status == "failed" for r in results)
    t = Table(title=f"objcam batch: {len(results)} captures, {failed} failed ({engine_note})")
    for col in ("capture", "status", "time", "note"):
        t.add_column(col, overflow="fold")
    for r in results:
        style = "green" if r.status == "done" else "red"
        t.add_row(escape(r.capture), f"[{style}]{r.status}[/]", f"{r.seconds:.1f} s", escape(r.note))
    Console(stderr=False, highlight=False).print(t)
