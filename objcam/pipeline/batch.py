"""``objcam run C1 C2 ... [--cluster SPEC]``: many captures, each capture's stages in order, on one cluster.

Without ``--cluster`` the captures run one after another in this process. With it, up to one capture per core of
this machine runs at a time, each in its own process (a capture's own work -- its samples, auto's renders, the
gather's set-up -- runs where the pipeline runs), and every capture's transport shards go to the one cluster, so
the captures' stages interleave there instead of queueing (objcam.pipeline.cluster, objcam.transport.shards).
A capture that fails, its process included, is reported and the others go on; each capture's own output is
printed whole when it ends, then one summary table; the exit status is the number of captures that failed. One
capture without ``--cluster`` never comes here (the plain in-process run, with no Dask import).
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
    started: float = 0.0  # seconds after the batch began (captures run at once start together)


def run_batch(args: argparse.Namespace, run_one) -> int:
    """Run ``run_one(args_for_one_capture)`` per capture (args.capture plus args.more) under args.cluster's
    engine. One capture: as a plain run (its error raised); several: a summary table, exit status = failures.
    run_one must be a module-level function (it is sent to the captures' processes)."""
    from objcam.threads import cores

    captures = [args.capture, *getattr(args, "more", [])]
    if len(captures) > 1 and args.work is not None:
        raise ObjcamError("--work names one artifact folder and this run has several captures",
                          fix="drop --work (each capture keeps its artifacts in CAPTURE/objcam)")
    if len(set(map(str, captures))) != len(captures):
        raise ObjcamError("a capture is named twice in this run", fix="name each capture once")
    with _engine(args.cluster) as (engine_note, address):
        if len(captures) == 1:
            return run_one(args)
        jobs = min(len(captures), cores()) if address else 1
        t0 = time.perf_counter()
        if jobs > 1:
            results = _run_concurrently(args, captures, run_one, address, jobs, t0)
            engine_note += f", {jobs} captures at a time"
        else:
            results = [_run_here(args, cap, run_one, t0) for cap in captures]
        _print_summary(results, engine_note)
        return sum(r.status == "failed" for r in results)


def _one(args: argparse.Namespace, cap, **more) -> argparse.Namespace:
    return argparse.Namespace(**(vars(args) | {"capture": cap, "more": []} | more))


def _run_here(args: argparse.Namespace, cap, run_one, since: float) -> CaptureResult:
    """One capture in this process, its failure caught and reported (since: the batch's start)."""
    t0 = time.perf_counter()
    status, note = _guarded(run_one, _one(args, cap))
    if status == "failed":
        print(f"objcam: error: {cap}: {note}", file=sys.stderr)
    return CaptureResult(str(cap), status, time.perf_counter() - t0, note, t0 - since)


def _guarded(run_one, one: argparse.Namespace) -> tuple[str, str]:
    """(status, note) of ``run_one(one)``: an objcam error or a bug in one capture must not stop the others."""
    try:
        run_one(one)
        return "done", ""
    except ObjcamError as e:
        return "failed", str(e)
    except Exception as e:
        return "failed", one_line(f"{type(e).__name__}: {e}")


def _child(conn, one: argparse.Namespace, address: str, run_one) -> None:
    """A capture's process: its run on the cluster at ``address``; sends (status, note, its printed output)."""
    import io
    from contextlib import redirect_stdout

    out = io.StringIO()
    with redirect_stdout(out):
        try:
            with _engine(address):
                status, note = _guarded(run_one, one)
        except ObjcamError as e:  # the cluster itself (gone since the batch started it)
            status, note = "failed", str(e)
    conn.send((status, note, out.getvalue()))
    conn.close()


def _run_concurrently(args: argparse.Namespace, captures: list, run_one, address: str, jobs: int,
                      since: float) -> list[CaptureResult]:
    """The captures in ``jobs`` processes at a time (spawned: this one holds Dask's threads), each a client of
    the cluster at ``address``; results in the captures' order. Their progress bars are off (they would
    interleave); each capture's output is printed when it ends."""
    import multiprocessing as mp
    import signal
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    todo, running, done = list(captures), {}, {}
    while todo or running:
        while todo and len(running) < jobs:
            cap = todo.pop(0)
            recv, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_child, args=(send, _one(args, cap, quiet=True, cluster=address), address,
                                                    run_one), name=f"objcam {cap}", daemon=False)
            proc.start()
            send.close()  # the child holds the only writer: its end of the pipe reads EOF if it dies
            running[recv] = (proc, cap, time.perf_counter())
        for recv in wait(list(running)):
            proc, cap, t0 = running.pop(recv)
            try:
                status, note, printed = recv.recv()
            except EOFError:
                status, note, printed = "failed", "", ""
            proc.join()
            if not note and status == "failed":
                code = proc.exitcode
                why = f"killed by {signal.Signals(-code).name}" if code is not None and code < 0 else \
                    f"exit code {code}"
                note = f"its process ended without a result ({why})"
            sys.stdout.write(printed)
            if status == "failed":
                print(f"objcam: error: {cap}: {note}", file=sys.stderr)
            done[str(cap)] = CaptureResult(str(cap), status, time.perf_counter() - t0, note, t0 - since)
            recv.close()
    return [done[str(c)] for c in captures]


@contextmanager
def _engine(spec: str | None):
    """The transport engine for the run: shards on the cluster SPEC, else in-process. Yields (a note for the
    summary, the scheduler's address or None)."""
    if not spec:
        yield "in-process", None
        return
    from objcam.pipeline.cluster import connect
    from objcam.transport.engine import using
    from objcam.transport.shards import DaskEngine

    with connect(spec) as client, using(DaskEngine(client)):
        yield f"transport shards on {spec}", client.scheduler.address


def _print_summary(results: list[CaptureResult], engine_note: str) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    failed = sum(r.status == "failed" for r in results)
    t = Table(title=f"objcam batch: {len(results)} captures, {failed} failed ({engine_note})")
    for col in ("capture", "status", "started", "time", "note"):
        t.add_column(col, overflow="fold")
    for r in results:
        style = "green" if r.status == "done" else "red"
        t.add_row(escape(r.capture), f"[{style}]{r.status}[/]", f"+{r.started:.1f} s", f"{r.seconds:.1f} s",
                  escape(r.note))
    Console(stderr=False, highlight=False).print(t)
