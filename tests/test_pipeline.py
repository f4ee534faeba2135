"""Stage engine: caching (skip, invalidate, downstream reruns), atomic installs, resume after a kill, the lock,
and --set validation. Uses a package of three toy stages so the tests are about the engine alone."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from objcam.errors import ObjcamError
from objcam.pipeline import graph
from objcam.pipeline.engine import Pipeline, parse_overrides

TOY = {
    "first": '''
NAME = "first"; DEPS = (); VERSION = "1"
from pydantic import BaseModel
from objcam.pipeline.stage import StageOutputs
class Params(BaseModel):
    scale: float = 2.0
def input_files(capture):
    return [capture / "input.txt"]
def run(inputs, params):
    import os, time
    v = float((inputs.capture / "input.txt").read_text()) * params.scale
    (inputs.out / "value.txt").write_text(str(v))
    log = inputs.capture.parent / "runs.log"
    with open(log, "a") as f: f.write("first\\n")
    return StageOutputs(metrics={"value": v}, summary=f"value {v}")
''',
    "second": '''
NAME = "second"; DEPS = ("first",); VERSION = "1"
from pydantic import BaseModel
from objcam.pipeline.stage import StageOutputs
class Params(BaseModel):
    offset: float = 1.0
    sleep: float = 0.0
def run(inputs, params):
    import time
    v = float((inputs.upstream["first"] / "value.txt").read_text()) + params.offset
    (inputs.out / "partial.txt").write_text("half")
    time.sleep(params.sleep)
    (inputs.out / "value.txt").write_text(str(v))
    with open(inputs.capture.parent / "runs.log", "a") as f: f.write("second\\n")
    return StageOutputs(metrics={"value": v})
''',
    "third": '''
NAME = "third"; DEPS = ("first",); VERSION = "1"
from pydantic import BaseModel
from objcam.pipeline.stage import StageOutputs
class Params(BaseModel):
    fail: bool = False
def run(inputs, params):
    if params.fail:
        raise ValueError("boom")
    (inputs.out / "ok.txt").write_text("ok")
    with open(inputs.capture.parent / "runs.log", "a") as f: f.write("third\\n")
    return StageOutputs()
''',
}


@pytest.fixture()
def toy(tmp_path, monkeypatch):
    pkg = tmp_path / "pkgs" / "toystages"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    for name, src in TOY.items():
        (pkg / f"{name}.py").write_text(textwrap.dedent(src))
    monkeypatch.syspath_prepend(str(tmp_path / "pkgs"))
    monkeypatch.setattr(graph, "STAGES", ("first", "second", "third"))
    monkeypatch.setattr(graph, "PACKAGE", "toystages")
    graph.stage_module.cache_clear()
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "input.txt").write_text("3")
    yield capture
    graph.stage_module.cache_clear()
    for name in list(sys.modules):
        if name.startswith("toystages"):
            del sys.modules[name]


def runs(capture: Path) -> list[str]:
    log = capture.parent / "runs.log"
    return log.read_text().split() if log.exists() else []


def test_runs_then_skips_unchanged(toy):
    reps = Pipeline(toy).run()
    assert [r.status for r in reps] == ["ran", "ran", "ran"]
    assert float((toy / "objcam" / "second" / "value.txt").read_text()) == 7.0
    rec = json.loads((toy / "objcam" / "first" / "stage.json").read_text())
    assert rec["params"] == {"scale": 2.0} and rec["inputs"]["input.txt"] != "missing"
    assert rec["wall_seconds"] >= 0 and rec["peak_rss_mb"] > 0 and rec["metrics"]["value"] == 6.0
    reps = Pipeline(toy).run()
    assert [r.status for r in reps] == ["cached"] * 3
    assert runs(toy) == ["first", "second", "third"]


def test_param_change_reruns_stage_and_downstream_only(toy):
    Pipeline(toy).run()
    reps = Pipeline(toy, overrides={"second": {"offset": 5.0}}).run()
    assert {r.stage: r.status for r in reps} == {"first": "cached", "second": "ran", "third": "cached"}
    assert float((toy / "objcam" / "second" / "value.txt").read_text()) == 11.0
    reps = Pipeline(toy, overrides={"first": {"scale": 1.0}}, ).run()
    assert [r.status for r in reps] == ["ran", "ran", "ran"]


def test_input_content_change_invalidates(toy):
    Pipeline(toy).run()
    (toy / "input.txt").write_text("4")
    rows = {r["stage"]: r["state"] for r in Pipeline(toy).status()}
    assert rows == {"first": "stale", "second": "stale", "third": "stale"}
    reps = Pipeline(toy).run()
    assert [r.status for r in reps] == ["ran", "ran", "ran"]
    assert float((toy / "objcam" / "first" / "value.txt").read_text()) == 8.0
    # touching a file without changing it keeps the cache
    os.utime(toy / "input.txt")
    assert [r.status for r in Pipeline(toy).run()] == ["cached"] * 3


def test_force_reruns_downstream(toy):
    Pipeline(toy).run()
    reps = Pipeline(toy).run(force=["second"])
    assert {r.stage: r.status for r in reps} == {"first": "cached", "second": "ran", "third": "cached"}


def test_status_missing_then_done(toy):
    assert {r["state"] for r in Pipeline(toy).status()} == {"missing"}
    Pipeline(toy).run(until="first")
    st = {r["stage"]: r["state"] for r in Pipeline(toy).status()}
    assert st == {"first": "done", "second": "missing", "third": "missing"}


def test_failed_stage_leaves_no_artifact_and_keeps_others(toy):
    Pipeline(toy).run()
    with pytest.raises(ObjcamError, match="stage third failed: ValueError: boom"):
        Pipeline(toy, overrides={"third": {"fail": True}}).run()
    work = toy / "objcam"
    assert not list(work.glob(".tmp-*"))
    assert (work / "third.error.log").read_text().count("ValueError") >= 1
    # the previous complete artifact of 'third' is still in place, and still matches its own old key
    assert (work / "third" / "ok.txt").exists()


def test_bad_override_is_one_clear_line(toy):
    with pytest.raises(ObjcamError, match=r"bad --set for stage second: second.offset"):
        Pipeline(toy, overrides={"second": {"offset": "abc"}}).run()
    assert runs(toy) == []  # refused before any stage ran
    with pytest.raises(ObjcamError, match="no stage 'nope'"):
        parse_overrides(["nope.x=1"])
    assert parse_overrides(["second.offset=2.5", "third.fail=true"]) == {"second": {"offset": 2.5},
                                                                        "third": {"fail": True}}


def test_lock_blocks_a_second_run(toy):
    p1, p2 = Pipeline(toy), Pipeline(toy)
    with p1.lock():
        with pytest.raises(ObjcamError, match="holds the lock"):
            p2.run()
    assert len(p2.run()) == 3  # freed afterwards


def test_resume_after_kill(toy, tmp_path):
    """Kill a run in the middle of 'second': no half artifact; the rerun skips 'first' and finishes."""
    script = tmp_path / "driver.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(tmp_path / 'pkgs')!r})
        from objcam.pipeline import graph
        graph.STAGES = ("first", "second", "third"); graph.PACKAGE = "toystages"
        from objcam.pipeline.engine import Pipeline
        Pipeline({str(toy)!r}, overrides={{"second": {{"sleep": 30}}}}).run()
    """))
    proc = subprocess.Popen([sys.executable, str(script)])
    work = toy / "objcam"
    deadline = time.time() + 60
    while time.time() < deadline and not list(work.glob(".tmp-second-*/partial.txt")):
        time.sleep(0.05)
    assert list(work.glob(".tmp-second-*/partial.txt")), "the driver never reached stage 'second'"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert (work / "first" / "stage.json").exists()
    assert not (work / "second").exists()  # nothing half-written at the final path
    reps = Pipeline(toy).run()
    assert {r.stage: r.status for r in reps} == {"first": "cached", "second": "ran", "third": "ran"}
    assert not list(work.glob(".tmp-*"))
