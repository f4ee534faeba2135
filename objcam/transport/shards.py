"""The transport's column shards as Dask tasks (``objcam run --cluster``; objcam.transport.engine's interface).

The driver (the process running the pipeline) builds each model once -- the camera's samples and direct model,
the gather's matrices -- and pickles it into the stage's temporary folder (``_shards/``, removed before the stage
ends). A worker loads it once per camera (the Mitsuba scene is rebuilt from the scene artifact: the pickle holds
only the path), computes its shards and writes them as zarr chunks into that folder:

- direct light: one task per block of envmap rows, writing chunk [:, :, t0:t1] of ``_shards/<cam>/direct``
  (one zarr chunk per block), read back in order by the driver into A;
- indirect light (model auto, gather): one task per chunk of A's columns, adding its columns in place (chunks
  are disjoint, so tasks never write the same chunk);
- the Gram matrix: one task per pair of column blocks (I, J), each writing A_I^T A_J (float64) beside the
  shards; the driver assembles the blocks.

Every task is a pure function of its inputs: a task lost with its worker is run again elsewhere (Dask reschedules
it; ``retries`` more on errors) and writes the same bytes. Workers must see the work folder and the scene
artifact at the same paths as the driver (a shared filesystem) and import the same objcam.
"""

from __future__ import annotations

import os
import pickle
import shutil
import time
import uuid
from pathlib import Path
from typing import Iterator

import numpy as np

# per worker process: the last contexts loaded (path -> model), so a worker loads each camera's model once
_CONTEXTS: dict[str, object] = {}
_KEEP = 2
_STATS = ("rays_total", "rays_traced", "pairs_zero", "pairs_analytic", "pairs_traced", "pairs_refined",
          "pairs_settled")


def _write_context(path: Path, obj) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)
    return str(path)


def _context(path: str, runtime: tuple[str, dict]):
    """The model pickled at ``path``, loaded once per worker. runtime: (Mitsuba's variant, the driver's; worker
    processes per host, from the scheduler)."""
    obj = _CONTEXTS.get(path)
    if obj is None:
        c0 = time.process_time()
        from objcam.scene import use_mitsuba

        variant, per_host = runtime
        use_mitsuba(variant)
        _share_cores(per_host)
        with open(path, "rb") as f:
            obj = pickle.load(f)
        while len(_CONTEXTS) >= _KEEP:
            _CONTEXTS.pop(next(iter(_CONTEXTS)))
        _CONTEXTS[path] = obj
        _LOAD_CPU[0] += time.process_time() - c0
    return obj


def _share_cores(per_host: dict) -> None:
    """Dr.Jit's thread pool on a worker: this host's cores over the workers on it (at least one thread). Each
    worker runs one task at a time, its kernels on Dr.Jit's pool; a pool of every core in every worker puts
    several threads on each core (a LocalCluster of 2 on 2 cores: 4), which contend for it. (Session 15 measured
    the direct shards at 30% more CPU than the same blocks in-process; whether this closes that gap was not
    measurable on the loaded machine of session 16: bench/results.md.)"""
    import drjit as dr
    from distributed import get_worker

    from objcam.threads import cores

    try:
        host = get_worker().address.split("://")[-1].rsplit(":", 1)[0]
    except ValueError:  # not in a worker (a task run in-process by a test)
        return
    dr.set_thread_count(max(1, cores() // max(1, int(per_host.get(host, 1)))))


_LOAD_CPU = [0.0]  # this worker's CPU seconds spent loading contexts, reported by the next task (then reset)


def _cpu(c0: float) -> dict:
    """A task's CPU accounting: its process CPU since ``c0`` (a worker runs one task at a time, so that is the
    task's, Dr.Jit's threads included) and the part spent loading its context."""
    load, _LOAD_CPU[0] = _LOAD_CPU[0], 0.0
    return {"cpu": time.process_time() - c0, "load_cpu": load}


def _parts(dm) -> list:
    """The DirectModels inside a DirectModel or SplitDirect."""
    return [p for _, p in dm.parts] if hasattr(dm, "parts") else [dm]


def _stats(dm) -> list[list[int]]:
    return [[getattr(p.stats, k) for k in _STATS] for p in _parts(dm)]


def direct_task(ctx: str, runtime: tuple[str, dict], store: str, t0: int, t1: int) -> dict:
    """Direct-light columns of texels t0 .. t1 - 1 into ``store``'s chunk; returns the rays / pairs counted
    (``stats``, per part) and the CPU accounting."""
    import zarr

    c0 = time.process_time()
    dm = _context(ctx, runtime)
    before = _stats(dm)
    cols = dm.columns(np.arange(t0, t1, dtype=np.int64))
    zarr.open_array(store, mode="r+")[:, :, t0:t1] = cols
    return {"stats": [[a - b for a, b in zip(x, y)] for x, y in zip(_stats(dm), before)]} | _cpu(c0)


def indirect_task(ctx: str, runtime: tuple[str, dict], folder: str, a: int, b: int, keep: bool) -> dict:
    """A[:, :, a:b] += the gather's indirect columns, in place; returns the nodes' direct light ``E``
    (C, S, b - a) when ``keep`` (else None), ``seconds``, node shadow ``rays`` traced, and the CPU accounting."""
    import zarr

    c0 = time.process_time()
    gi = _context(ctx, runtime)
    t, rays = gi.seconds_columns, gi.dm.stats.rays_traced
    A = zarr.open_group(folder, mode="r+")["A"]
    A[:, :, a:b] = A[:, :, a:b] + gi.columns(a, b).astype(np.float32)
    E = gi.E[:, :, a:b].copy() if keep else None
    return {"E": E, "seconds": gi.seconds_columns - t, "rays": gi.dm.stats.rays_traced - rays} | _cpu(c0)


def gram_task(folder: str, i: tuple[int, int], j: tuple[int, int], out: str) -> dict:
    """The Gram block A_c[:, i0:i1]^T A_c[:, j0:j1] per channel (C, i1 - i0, j1 - j0) float64, saved to ``out``
    (column blocks: a task reads two column ranges of A, never all of it)."""
    import zarr

    c0 = time.process_time()
    A = zarr.open_group(folder, mode="r")["A"]
    ai = np.asarray(A[:, :, i[0]:i[1]], dtype=np.float64)
    aj = ai if j == i else np.asarray(A[:, :, j[0]:j[1]], dtype=np.float64)
    np.save(out, np.stack([ai[c].T @ aj[c] for c in range(ai.shape[0])]))
    return {"path": out} | _cpu(c0)


class DaskEngine:
    """The transport's shards on a ``distributed.Client``'s cluster (see the module docstring).

    retries: extra attempts of a task that raised (a task lost with its worker is rescheduled by Dask itself);
    on_result: called after each shard's result arrives (progress hooks; tests kill a worker from it)."""

    name = "dask"

    def __init__(self, client, retries: int = 2, on_result=None):
        self.client = client
        self.retries = int(retries)
        self.on_result = on_result
        self.tasks = 0
        self.seconds_driver_wait = 0.0
        self.cpu: dict[str, float] = {}  # the shards' CPU seconds per phase, and of loading contexts
        self.context_bytes = 0  # the largest pickled model a worker loads (its memory, roughly)

    # --------------------------------------------------------------------------------------------- helpers
    def _runtime(self) -> tuple[str, dict]:
        """What a worker needs besides a task's model: Mitsuba's variant, and the workers on each host."""
        import mitsuba as mi

        per_host: dict[str, int] = {}
        for w in self.client.scheduler_info().get("workers", {}).values():
            per_host[w.get("host", "")] = per_host.get(w.get("host", ""), 0) + 1
        return mi.variant(), per_host

    def _submit(self, fn, *args, tag: str):
        self.tasks += 1
        return self.client.submit(fn, *args, key=f"objcam-{tag}-{uuid.uuid4().hex[:12]}", pure=False,
                                  retries=self.retries)

    def _results(self, futures, phase: str) -> Iterator[dict]:
        """Each future's result, in submission order; its CPU accounting summed per phase."""
        for fut in futures:
            t0 = time.perf_counter()
            res = fut.result()
            self.seconds_driver_wait += time.perf_counter() - t0
            self.cpu[phase] = self.cpu.get(phase, 0.0) + res["cpu"]
            self.cpu["context_load"] = self.cpu.get("context_load", 0.0) + res["load_cpu"]
            if self.on_result is not None:
                self.on_result(self)
            yield res

    def _workers(self) -> int:
        return max(1, len(self.client.scheduler_info().get("workers", {})))

    @staticmethod
    def _shard_dir(folder: Path) -> Path:
        return Path(folder).parent / "_shards" / Path(folder).name

    # ------------------------------------------------------------------------------------------- the engine
    def direct_columns(self, dm, blocks: list[np.ndarray], folder: Path) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        import zarr

        from objcam.transport.storage import _compressor

        shard = self._shard_dir(folder)
        try:
            ctx = _write_context(shard / "direct.pkl", dm)
            self.context_bytes = max(self.context_bytes, os.path.getsize(ctx))
            first = [int(b[0]) for b in blocks]
            last = [int(b[-1]) + 1 for b in blocks]
            if any(b.size != e - s for b, s, e in zip(blocks, first, last)) or \
                    any(s != i * (last[0] - first[0]) for i, s in enumerate(first)):
                raise ValueError("direct_columns: blocks must be consecutive equal texel ranges from 0")
            # shards of q texels (q divides the block, so every shard is one chunk): a few per worker
            q = _shard_size(last[0] - first[0], len(blocks), self._workers())
            spans = [[(a, min(a + q, e)) for a in range(s, e, q)] for s, e in zip(first, last)]
            c, m = _parts(dm)[0].c, dm.m
            store = str(shard / "direct")
            zarr.create_array(store, shape=(c, m, max(last)), chunks=(c, m, q), dtype="float32",
                              compressors=_compressor(), fill_value=0.0, zarr_format=3)
            runtime = self._runtime()
            futs = [[self._submit(direct_task, ctx, runtime, store, a, b, tag="direct") for a, b in sp] for sp in spans]
            arr = zarr.open_array(store, mode="r")
            parts = _parts(dm)
            for tex, s, e, fs in zip(blocks, first, last, futs):
                for res in self._results(fs, "direct"):
                    for p, d in zip(parts, res["stats"]):
                        for k, v in zip(_STATS, d):
                            setattr(p.stats, k, getattr(p.stats, k) + int(v))
                yield tex, np.asarray(arr[:, :, s:e])
        finally:
            shutil.rmtree(shard, ignore_errors=True)
            _prune(shard)

    def add_indirect(self, folder: Path, gi) -> None:
        import zarr

        shard = self._shard_dir(folder)
        try:
            A = zarr.open_group(str(folder), mode="r")["A"]
            n, step = A.shape[2], A.chunks[2]
            ctx = _write_context(shard / "gather.pkl", gi)
            self.context_bytes = max(self.context_bytes, os.path.getsize(ctx))
            if gi.keep_parts and gi.E is None:  # the nodes' direct light, filled from the shards' results
                gi.E = np.zeros((gi.channels, gi.dm.m, gi.texel_index.size), np.float32)
            runtime = self._runtime()
            spans = [(a, min(n, a + step)) for a in range(0, n, step)]
            futs = [self._submit(indirect_task, ctx, runtime, str(folder), a, b, bool(gi.keep_parts), tag="gather")
                    for a, b in spans]
            for (a, b), res in zip(spans, self._results(futs, "gather")):
                if res["E"] is not None:
                    gi.E[:, :, a:b] = res["E"]
                gi.seconds_columns += res["seconds"]
                gi.dm.stats.rays_traced += int(res["rays"])
        finally:
            shutil.rmtree(shard, ignore_errors=True)
            _prune(shard)

    def write_gram(self, folder: Path) -> float:
        import io

        import zarr

        from objcam.image_io import atomic_write_bytes
        from objcam.transport.storage import GRAM

        t0 = time.perf_counter()
        shard = self._shard_dir(folder)
        shard.mkdir(parents=True, exist_ok=True)
        try:
            A = zarr.open_group(str(folder), mode="r")["A"]
            c, n, chunk = A.shape[0], A.shape[2], A.chunks[2]
            # p column blocks (whole chunks), p (p + 1) / 2 block products: about two per worker
            n_chunks = -(-n // chunk)
            p = max(1, min(n_chunks, int(np.sqrt(4 * self._workers()))))
            per = chunk * -(-n_chunks // p)  # columns per block, whole chunks
            cols = [(a, min(n, a + per)) for a in range(0, n, per)]
            pairs = [(i, j) for a, i in enumerate(cols) for j in cols[a:]]
            futs = [self._submit(gram_task, str(folder), i, j, str(shard / f"gram{k}.npy"), tag="gram")
                    for k, (i, j) in enumerate(pairs)]
            G = np.zeros((c, n, n))
            for (i, j), res in zip(pairs, self._results(futs, "gram")):
                blk = np.load(res["path"])
                G[:, i[0]:i[1], j[0]:j[1]] = blk
                G[:, j[0]:j[1], i[0]:i[1]] = np.transpose(blk, (0, 2, 1))
            G = 0.5 * (G + np.transpose(G, (0, 2, 1)))  # exactly symmetric, as objcam.solvers.gram
            buf = io.BytesIO()
            np.save(buf, G)
            atomic_write_bytes(Path(folder) / GRAM, buf.getvalue())
        finally:
            shutil.rmtree(shard, ignore_errors=True)
            _prune(shard)
        return time.perf_counter() - t0

    def metrics(self) -> dict:
        """The engine's counts since the last call (one camera's build; the engine serves a whole batch)."""
        out = {"engine": self.name, "engine_workers": self._workers(), "engine_tasks": self.tasks,
               "engine_driver_wait_seconds": round(self.seconds_driver_wait, 3),
               "engine_context_mb": round(self.context_bytes / 2**20, 1)}
        out |= {f"engine_cpu_{k}_seconds": round(v, 3) for k, v in self.cpu.items()}
        self.tasks, self.seconds_driver_wait, self.cpu, self.context_bytes = 0, 0.0, {}, 0
        return out


def _shard_size(block: int, n_blocks: int, workers: int, per_worker: int = 4) -> int:
    """The largest divisor of ``block`` that makes at least ``per_worker`` shards per worker over ``n_blocks``
    blocks (a small scene's one block still spreads over the cluster; a large one keeps its blocks whole)."""
    want = -(-per_worker * workers // max(1, n_blocks))  # shards per block
    if want <= 1:
        return block
    for q in range(max(1, block // want), 0, -1):
        if block % q == 0:
            return q
    return 1


def _prune(shard: Path) -> None:
    """Remove ``_shards/`` once empty (it must not stay among the stage's artifacts)."""
    for p in (shard.parent,):
        try:
            p.rmdir()
        except OSError:
            pass
