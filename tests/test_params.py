"""Stage parameters (issue 23): `objcam params` lists every one the stages accept, each stage's --help its own, a
typo gets a suggestion, and capture.toml's [params.<stage>] keeps a setting that --set overrides for one run,
with a rerun that changes a setting saying so."""

from __future__ import annotations

import json
import re

import pytest
from pydantic import BaseModel

from objcam.errors import ObjcamError
from objcam.pipeline import graph
from objcam.pipeline.cache import manifest_digest
from objcam.pipeline.cli import main
from objcam.pipeline.engine import Pipeline, parse_overrides
from objcam.schemas.capture import CaptureManifest
from tests import test_pipeline

toy = test_pipeline.toy  # the toy-stage fixture
runs = test_pipeline.runs

PARAM_LINE = re.compile(r"^  (\S+)  \((.+)\) = (.*)$")


def _fields(model: type[BaseModel], prefix: str = "") -> dict[str, object]:
    """Every field the model accepts, nested models spelled with dots: the pydantic models themselves."""
    out: dict[str, object] = {}
    for name, f in model.model_fields.items():
        if isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel):
            out.update(_fields(f.annotation, f"{prefix}{name}."))
        else:
            out[prefix + name] = f
    return out


def _listed(text: str) -> dict[str, tuple[str, str]]:
    return {m.group(1): (m.group(2), m.group(3)) for m in map(PARAM_LINE.match, text.splitlines()) if m}


def test_params_lists_every_parameter(capsys):
    assert main(["params"]) == 0
    out = capsys.readouterr().out
    listed = _listed(out)
    want = {f"{s}.{n}": f for s in graph.STAGES for n, f in _fields(graph.stage_module(s).Params).items()}
    assert set(listed) == set(want)
    assert len(want) > 100  # the issue counted 114
    for name, f in want.items():
        if f.description:  # each description is printed (wrapped) after its parameter
            assert " ".join(f.description.split()[:4]) in " ".join(out.split()), name
    assert listed["transport.samples"][0] == "int"
    assert listed["solve.method"][1] == repr(graph.stage_module("solve").Params().method)


def test_each_stage_help_lists_its_own(capsys):
    for stage in graph.STAGES:
        with pytest.raises(SystemExit) as e:
            main([stage, "--help"])
        assert e.value.code == 0
        listed = _listed(capsys.readouterr().out)
        assert set(listed) == set(_fields(graph.stage_module(stage).Params)), stage


@pytest.mark.parametrize("setting, hint", [
    ("transport.sample=4", "did you mean transport.samples?"),
    ("geometry.silhouette.tolerence=0.1", "did you mean geometry.silhouette.tolerance?"),
    ("solv.method=paper", "did you mean solve?"),
])
def test_a_typo_gets_a_suggestion(tmp_path, capsys, setting, hint):
    (tmp_path / "cap").mkdir()
    assert main(["run", str(tmp_path / "cap"), "--set", setting]) == 2
    err = capsys.readouterr().err
    assert hint in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "cap" / "objcam").exists()


def test_nested_setting_reaches_the_model(tmp_path):
    (tmp_path / "cap").mkdir()
    pipe = Pipeline(tmp_path / "cap", overrides=parse_overrides(["geometry.silhouette.tolerance=0.07"]))
    p = pipe.params("geometry")
    assert p.silhouette.tolerance == 0.07
    assert p.silhouette.model_dump() | {"tolerance": 0.07} == p.silhouette.model_dump()


def test_capture_toml_keeps_settings(tmp_path):
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.toml").write_text('[scene]\nobject = "o.ply"\n\n[[targets]]\nname = "t0"\nimage = "t.exr"\n'
                                      'camera = "t.json"\n\n[params.solve]\nmethod = "paper"\n\n'
                                      "[params.geometry.silhouette]\ntolerance = 0.05\n")
    assert CaptureManifest.load(cap).params["solve"] == {"method": "paper"}
    assert Pipeline(cap).params("solve").method == "paper"
    assert Pipeline(cap).params("geometry").silhouette.tolerance == 0.05
    assert Pipeline(cap, overrides=parse_overrides(["solve.method=exact"])).params("solve").method == "exact"
    # a setting reaches the stage's key through its params alone: the capture's other stages keep theirs
    digest = manifest_digest(cap / "capture.toml")
    text = (cap / "capture.toml").read_text()
    (cap / "capture.toml").write_text(text.replace('"paper"', '"exact"'))
    assert manifest_digest(cap / "capture.toml") == digest
    (cap / "capture.toml").write_text(text.replace('name = "t0"', 'name = "t1"'))
    assert manifest_digest(cap / "capture.toml") != digest
    for bad, hint in (("[params.solv]\nmethod = 1\n", "did you mean solve?"),
                      ("[params.transport]\nsample = 4\n", "did you mean transport.samples?")):
        (cap / "capture.toml").write_text(text.split("[params.solve]")[0] + bad)
        with pytest.raises(ObjcamError, match=re.escape(hint)) as e:
            Pipeline(cap).params("transport")
        assert "capture.toml" in str(e.value)


def test_run_and_status_compare_against_capture_toml(toy):
    (toy / "capture.toml").write_text("[params.second]\noffset = 5.0\n")
    value = lambda: float((toy / "objcam" / "second" / "value.txt").read_text())  # noqa: E731
    Pipeline(toy).run()
    assert value() == 3 * 2 + 5
    assert [r.status for r in Pipeline(toy).run()] == ["cached"] * 3  # a plain run keeps the kept setting
    reps = {r.stage: r for r in Pipeline(toy, overrides=parse_overrides(["second.offset=1"])).run()}
    assert reps["second"].status == "ran" and value() == 7
    assert "params changed since the last run: second.offset 5.0 -> 1.0" in reps["second"].summary
    rows = {r["stage"]: r for r in Pipeline(toy).status()}
    assert rows["second"]["state"] == "stale" and rows["second"]["changed"] == ["second.offset 1.0 -> 5.0"]
    assert rows["first"]["state"] == "done" and rows["first"]["changed"] == []
    reps = {r.stage: r for r in Pipeline(toy).run()}
    assert value() == 11 and "second.offset 1.0 -> 5.0" in reps["second"].summary
    rec = json.loads((toy / "objcam" / "second" / "stage.json").read_text())
    assert rec["params"]["offset"] == 5.0
    assert runs(toy) == ["first", "second", "third", "second", "second"]
