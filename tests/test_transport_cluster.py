"""objcam on a Dask cluster: the transport's shards (objcam.transport.shards) give the in-process A, Gram matrix,
bounce parts and envmaps; a worker killed mid-transport changes nothing; a batch of captures on one cluster
completes the good ones past a failing one; the default path never imports Dask; cluster specs and config."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from objcam.errors import ObjcamError
from objcam.pipeline.stage import StageInputs
from objcam.stages import transport as stage
from tests.test_transport import ENV_H, _write_artifact

ROOT = Path(__file__).resolve().parents[1]
# model auto with the gather forced (a tiny noise), an unknown support albedo (bounce parts kept), 16-column
# chunks: several direct, gather and Gram shards on a 32 x 32 target
PARAMS = dict(env_height=ENV_H, model="auto", auto_noise=1e-6, indirect="gather", chunk_columns=16,
              subpixel_samples=8, object_subpixel_samples=16, object_samples=4, gather_rays=32, gather_node_rays=16,
              auto_columns=4, auto_spp=4)


def test_cluster_specs():
    from objcam.pipeline.cluster import parse

    assert parse("local:3").workers == 3 and parse("local").kind == "local" and parse("local").workers >= 1
    assert parse("tcp://10.0.0.5:8786").address == "tcp://10.0.0.5:8786"
    assert parse("my-slurm").name == "my-slurm"
    for bad in ("local:0", "tcp://host", "http://x:1", "two words", ""):
        with pytest.raises(ObjcamError, match="fix:"):
            parse(bad)


def test_named_clusters_come_from_dask_config():
    import dask.config

    from objcam.pipeline.cluster import named_config

    with dask.config.set({"objcam.clusters": {"lab": {"kind": "slurm", "jobs": 4,
                                                      "options": {"cores": 8, "memory": "32GB"}},
                                              "odd": {"kind": "kubernetes"}}}):
        assert named_config("lab") == {"kind": "slurm", "jobs": 4, "options": {"cores": 8, "memory": "32GB"}}
        with pytest.raises(ObjcamError, match="defined: lab, odd"):
            named_config("nope")
        with pytest.raises(ObjcamError, match="kind is 'kubernetes'"):
            named_config("odd")


def test_the_default_path_never_imports_dask(tmp_path):
    """The CLI imported and an in-process transport built: neither dask nor distributed is loaded."""
    code = f"""
import sys
from pathlib import Path
import objcam.pipeline.cli  # noqa: F401
from objcam.pipeline.stage import StageInputs
from objcam.stages import transport as stage
from tests.test_transport import _write_artifact
art = Path({str(tmp_path / 'art')!r}); _write_artifact(art)
out = Path({str(tmp_path / 'out')!r}); out.mkdir()
m = stage.run(StageInputs(capture=art, upstream={{"scene": art}}, out=out), stage.Params(env_height=4, model="direct",
              subpixel_samples=4, object_subpixel_samples=4, object_samples=4)).metrics
assert m["engine"] == "in-process", m
loaded = sorted(n for n in sys.modules if n.split(".")[0] in ("dask", "distributed", "dask_jobqueue"))
assert not loaded, loaded
print("ok")
"""
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                       env=os.environ | {"OBJCAM_QUIET": "1"})
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-2000:]


@pytest.fixture(scope="module")
def client():
    from objcam.pipeline.cluster import connect

    with connect("local:2") as c:  # started and closed here
        yield c


def test_local_workers_run_without_dasks_profiler(client):
    """connect("local:N") starts its workers without Dask's statistical profiler (its 10 ms stack samples of every
    thread cost ~2 CPU s of the demo's transport)."""
    import dask.config

    got = client.run(lambda: dask.config.get("distributed.worker.profile.enabled"))
    assert len(got) == 2 and not any(got.values()), got
    assert dask.config.get("distributed.worker.profile.enabled")  # the driver's own config is left as it was


def test_workers_are_warmed_when_they_start(client):
    """connect() registers a plugin that imports the shards' modules and Mitsuba on every worker as it starts, so
    a capture's first shards do not pay for them (~0.5 CPU s per worker)."""
    import sys

    from objcam.pipeline.cluster import WARM_MODULES

    def warm() -> tuple:
        mi = sys.modules.get("mitsuba")
        return all(m in sys.modules for m in WARM_MODULES), bool(mi is not None and mi.variant())

    got = client.run(warm)
    assert len(got) == 2 and all(v == (True, True) for v in got.values()), got
    assert "objcam-warm" in client.run(lambda dask_worker: list(dask_worker.plugins))[next(iter(got))]
    # broken: a fresh process has none of them until something imports them
    r = subprocess.run([sys.executable, "-c", "import sys, objcam.pipeline.cluster as c; "
                        "print(any(m in sys.modules for m in c.WARM_MODULES))"], capture_output=True, text=True)
    assert r.stdout.strip() == "False", r.stderr[-2000:]


def die_once(marker: str, fn, *args):
    """Run ``fn(*args)``, but the first call anywhere (a file created exclusively) kills its worker process
    instead: os._exit, no exception, the task is lost with the worker."""
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return fn(*args)
    os._exit(1)


def _build(art: Path, out: Path) -> dict:
    out.mkdir(parents=True)
    return stage.run(StageInputs(capture=art, upstream={"scene": art}, out=out), stage.Params(**PARAMS)).metrics


def _load(out: Path) -> dict:
    import zarr

    g = zarr.open_group(str(out / "cam0"), mode="r")
    res = {"A": np.asarray(g["A"][...]), "texel_index": np.asarray(g["texel_index"][...]),
           "gram": np.load(out / "cam0" / "gram.npy")}
    with np.load(out / "cam0" / "bounce.npz") as z:
        res["E"] = z["E"]
    return res


def test_sharded_transport_equals_in_process_with_a_worker_killed(client, tmp_path):
    from objcam.transport.engine import using
    from objcam.transport.shards import DaskEngine

    art = tmp_path / "art"
    _write_artifact(art, sup=None)  # unknown support albedo: the gather keeps its bounce parts
    ref_m = _build(art, tmp_path / "ref")
    assert ref_m["model"] == "direct+indirect" and ref_m["engine"] == "in-process"
    marker = str(tmp_path / "killed")

    class Killing(DaskEngine):
        def _submit(self, fn, *args, tag):  # every shard behind die_once: the first one takes its worker down
            return super()._submit(die_once, marker, fn, *args, tag=tag)

    pids = set(client.run(os.getpid).values())
    with using(Killing(client)):
        m = _build(art, tmp_path / "dask")
    assert os.path.exists(marker)  # a worker really died holding a shard
    assert m["engine"] == "dask" and m["engine_tasks"] >= 8 and m["model"] == "direct+indirect"
    assert set(client.run(os.getpid).values()) != pids  # the nanny replaced the killed worker
    ref, got = _load(tmp_path / "ref"), _load(tmp_path / "dask")
    assert np.array_equal(ref["texel_index"], got["texel_index"])
    for k in ("A", "E"):  # the same bytes: every column depends on its texel and the seed only
        assert np.array_equal(ref[k], got[k]), k
    assert np.abs(got["gram"] - ref["gram"]).max() <= 1e-6 * np.abs(ref["gram"]).max()  # summed by row blocks
    for k in ("rays_traced", "pairs_traced", "gather_node_direct_rays", "texels_kept"):
        assert m[k] == ref_m[k], k  # the counts come back from the workers
    assert not any((tmp_path / "dask").rglob("_shards"))  # no shard left among the artifacts


def _tiny_capture(folder: Path, envmap: str) -> None:
    from objcam.synth.capture import SynthParams, synthesize

    synthesize(folder, SynthParams(object="sphere", object_height=0.04, envmap=envmap, envmap_height=16,
                                   cameras=[{"width": 40, "height": 40, "distance": 0.25, "elevation_deg": 55.0}],
                                   spp=16, max_depth=2, noise=False))


SETS = ["transport.env_height=8", "transport.model=auto", "transport.auto_noise=1e-6", "transport.chunk_columns=16",
        "transport.gather_rays=32", "transport.gather_node_rays=16", "transport.subpixel_samples=8",
        "transport.object_subpixel_samples=16", "solve.prior=smooth"]


def test_a_batch_on_a_cluster_completes_past_a_failing_capture(client, tmp_path, capsys, monkeypatch):
    """objcam run C1 BAD C2 --cluster tcp://...: two captures at a time, each in its own process (C1 and BAD start
    together, C2 when BAD fails), C1 and C2 running at the same time on the cluster; C1 and C2 solved, exit status
    1, one summary table; C1's envmap equals its in-process twin's."""
    from objcam.image_io import read_exr
    from objcam.pipeline import batch
    from objcam.pipeline.cli import main

    monkeypatch.setattr("objcam.threads.cores", lambda: 2)  # two captures at a time on any machine
    summary = []
    show = batch._print_summary
    monkeypatch.setattr(batch, "_print_summary", lambda results, note: (summary.extend(results), show(results, note)))

    c1, c2, bad = tmp_path / "c1", tmp_path / "c2", tmp_path / "bad"
    _tiny_capture(c1, "courtyard")
    _tiny_capture(c2, "forest")
    bad.mkdir()
    (bad / "capture.toml").write_text("this is not toml = [\n")
    twin = tmp_path / "twin"
    shutil.copytree(c1, twin)
    sets = [a for s in SETS for a in ("--set", s)]
    assert main(["run", str(twin), "-q", "--until", "solve", *sets]) == 0
    capsys.readouterr()
    rc = main(["run", str(c1), str(bad), str(c2), "-q", "--until", "solve", "--cluster",
               client.scheduler_info()["address"], *sets])
    out = capsys.readouterr()
    assert rc == 1
    title = " ".join(out.out.split())  # the table's title may wrap
    assert "3 captures, 1 failed" in title and "2 captures at a time" in title
    assert "capture.toml" in out.err and "Traceback" not in out.err
    r1, rbad, r2 = summary
    assert [r.status for r in summary] == ["done", "failed", "done"] and "capture.toml" in rbad.note
    assert r2.started < r1.started + r1.seconds  # C2 began before C1 ended: the captures interleave
    assert f"objcam: {c1}" in out.out and f"objcam: {c2}" in out.out  # each capture's own table, printed whole
    for c in (c1, c2):
        rec = json.loads((c / "objcam" / "transport" / "stage.json").read_text())
        assert rec["metrics"]["engine"] == "dask" and rec["metrics"]["model"] == "direct+indirect"
    env, ref = read_exr(c1 / "objcam/solve/t0/envmap.exr"), read_exr(twin / "objcam/solve/t0/envmap.exr")
    assert np.abs(env - ref).max() <= 1e-6 * np.abs(ref).max()
    assert not np.array_equal(env, read_exr(c2 / "objcam/solve/t0/envmap.exr"))  # two captures, two answers
