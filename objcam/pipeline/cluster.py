"""``--cluster SPEC``: the Dask cluster the transport's shards run on (objcam.transport.shards).

SPEC is one of

- ``local`` or ``local:N``: a LocalCluster of N worker processes, one task at a time each, on this machine
  (default: one per core);
- ``tcp://HOST:PORT`` (or ``tls://``): an existing scheduler (``dask scheduler`` and ``dask worker`` started
  elsewhere, on machines that share the work folder);
- ``NAME``: a cluster defined in Dask's configuration (``~/.config/dask/*.yaml``, or the folder in
  ``$DASK_CONFIG``) under ``objcam.clusters.NAME``: ``kind`` (slurm, pbs, sge, lsf, htcondor, oar, moab:
  dask-jobqueue's clusters; or local), ``jobs`` (how many batch jobs to start) and ``options`` (the cluster
  class's keyword arguments: cores, memory, walltime, queue, account, ...). README "Running a batch on a Slurm
  cluster" has an example.

Only ``objcam run --cluster`` imports this module, and only it imports Dask.
"""

from __future__ import annotations

import re
from contextlib import contextmanager
from dataclasses import dataclass

from objcam.errors import ObjcamError

JOBQUEUE = {"slurm": "SLURMCluster", "pbs": "PBSCluster", "sge": "SGECluster", "lsf": "LSFCluster",
            "htcondor": "HTCondorCluster", "oar": "OARCluster", "moab": "MoabCluster"}
_FIX = "use local, local:N, tcp://HOST:PORT or the name of a cluster under objcam.clusters in Dask's config"


@dataclass(frozen=True)
class ClusterSpec:
    kind: str  # local | address | named
    workers: int = 0  # local: worker processes
    address: str = ""  # address: the scheduler
    name: str = ""  # named: the key under objcam.clusters


def parse(spec: str) -> ClusterSpec:
    """The cluster SPEC names, or a one-line ObjcamError."""
    from objcam.threads import cores

    spec = (spec or "").strip()
    m = re.fullmatch(r"local(?::(\d+))?", spec)
    if m:
        n = int(m.group(1)) if m.group(1) else cores()
        if n < 1:
            raise ObjcamError(f"--cluster {spec}: a LocalCluster needs at least one worker", fix="use local:1 or more")
        return ClusterSpec("local", workers=n)
    if re.fullmatch(r"(tcp|tls)://[^\s/:]+:\d+", spec):
        return ClusterSpec("address", address=spec)
    if re.fullmatch(r"[A-Za-z][A-Za-z0-9_.-]*", spec):
        return ClusterSpec("named", name=spec)
    raise ObjcamError(f"--cluster {spec!r}: not a cluster spec", fix=_FIX)


def named_config(name: str) -> dict:
    """``objcam.clusters.NAME`` from Dask's configuration, checked."""
    import dask.config

    clusters = dask.config.get("objcam.clusters", default={}) or {}
    cfg = clusters.get(name)
    where = "~/.config/dask/objcam.yaml (or $DASK_CONFIG)"
    if cfg is None:
        have = ", ".join(sorted(clusters)) or "none"
        raise ObjcamError(f"--cluster {name}: no cluster of that name in Dask's config (defined: {have})",
                          fix=f"define objcam.clusters.{name} in {where} (README: running a batch on Slurm), "
                              "or use local[:N] / tcp://HOST:PORT")
    kind = str(cfg.get("kind", "")).lower()
    if kind != "local" and kind not in JOBQUEUE:
        raise ObjcamError(f"--cluster {name}: objcam.clusters.{name}.kind is {kind or 'missing'!r}",
                          fix=f"set kind to one of local, {', '.join(JOBQUEUE)} in {where}")
    opts = cfg.get("options", {}) or {}
    if not isinstance(opts, dict):
        raise ObjcamError(f"--cluster {name}: objcam.clusters.{name}.options must be a mapping",
                          fix=f"write the cluster's keyword arguments under options: in {where}")
    jobs = cfg.get("jobs", 1)
    if not isinstance(jobs, int) or jobs < 1:
        raise ObjcamError(f"--cluster {name}: objcam.clusters.{name}.jobs must be a positive integer",
                          fix=f"set jobs: 1 or more in {where}")
    return {"kind": kind, "options": dict(opts), "jobs": jobs}


#: the modules a transport shard runs (objcam.transport.shards' tasks and the models they unpickle)
WARM_MODULES = ("objcam.transport.shards", "objcam.transport.direct", "objcam.transport.gather",
                "objcam.transport.geometry", "zarr")


def _warm_plugin():
    """A Dask worker plugin that imports WARM_MODULES and Mitsuba (its default variant) when a worker starts.

    What a worker's first shard would otherwise spend before its first ray: ~0.5 CPU s per worker on this
    project's machine (the objcam and zarr imports 0.46 s, Mitsuba's 0.2 s), paid once per worker's life either
    way, but here while the driver is still preparing the capture instead of on the first shards' critical path,
    and outside each capture's transport (bench/results.md, issue 25, session 24). Best effort: a worker that
    cannot import them fails its first shard with the real error instead."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class Warm(WorkerPlugin):
        name = "objcam-warm"

        def setup(self, worker) -> None:
            import importlib

            try:
                for m in WARM_MODULES:
                    importlib.import_module(m)
                from objcam.scene import use_mitsuba

                use_mitsuba()
            except Exception:  # (reported by the first shard that needs it)
                pass

    return Warm()


@contextmanager
def connect(spec: str, timeout: float = 60.0):
    """A ``distributed.Client`` on the cluster SPEC names, closed (with the cluster it started) on exit."""
    from objcam.threads import cores

    cs = parse(spec)
    from distributed import Client, LocalCluster

    cluster = None
    try:
        if cs.kind == "local":
            import dask.config

            # one task at a time per worker; its Dr.Jit kernels use Dr.Jit's own thread pool (objcam.transport.shards).
            # Without Dask's statistical profiler (it samples every thread's stack every 10 ms, Dr.Jit's too): it
            # cost ~2 CPU s of the demo's ~19 on the cluster, +23-25% against +11-20% overhead (bench/results.md)
            with dask.config.set({"distributed.worker.profile.enabled": False}):
                cluster = LocalCluster(n_workers=cs.workers, threads_per_worker=1, processes=True,
                                       dashboard_address=":0", memory_limit=0 if cs.workers <= cores() else "auto")
            client = Client(cluster)
        elif cs.kind == "address":
            try:
                client = Client(cs.address, timeout=timeout)
            except OSError as e:
                raise ObjcamError(f"--cluster {cs.address}: no Dask scheduler answers there ({e})",
                                  fix="start one (dask scheduler; dask worker ADDRESS on each machine) or check "
                                      "the address") from None
        else:
            cfg = named_config(cs.name)
            if cfg["kind"] == "local":
                cluster = LocalCluster(**({"threads_per_worker": 1, "dashboard_address": None} | cfg["options"]))
            else:
                import dask_jobqueue

                cluster = getattr(dask_jobqueue, JOBQUEUE[cfg["kind"]])(**cfg["options"])
                cluster.scale(jobs=cfg["jobs"])
            client = Client(cluster)  # batch jobs join when the queue starts them; shards wait for them
        try:
            client.register_plugin(_warm_plugin(), name="objcam-warm")  # every worker, and those that join later
            yield client
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()
