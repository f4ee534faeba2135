"""Issue 24 on the real stages of a tiny capture (16 x 12 px, 8 x 16 envmap, direct light; ~4 s a run): a damaged
or missing artifact of every stage is detected and rebuilt to the same content, a run killed (-9) inside several
stages resumes to the same artifacts, a comment in capture.toml reruns nothing, the transport's size is
checked before it is built, and a malformed truth is a user error."""

from __future__ import annotations

import hashlib
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from objcam.image_io import read_exr, write_exr
from objcam.pipeline.cli import main
from objcam.pipeline.engine import Pipeline, parse_overrides
from tests.test_bad_input import assert_one_line_error, make_capture

SETS = ["--set", "transport.env_height=8", "--set", "transport.model=direct"]
STAGES = ("scene", "transport", "solve", "evaluate", "analysis", "report")
# keys of JSON artifacts that hold wall times or dates, not results
_TIMING = ("second", "time", "finished", "wall", "load_average", "peak_rss", "duration")


def _json_content(v):
    if isinstance(v, dict):
        return {k: _json_content(x) for k, x in v.items() if not any(t in k for t in _TIMING)}
    if isinstance(v, list):
        return [_json_content(x) for x in v]
    return v


def content(work: Path) -> dict[str, str]:
    """A digest per artifact of what it holds: EXR pixels (not their DateTime), JSON without timings, other files'
    bytes; the report page (it shows the run's timings), the stage records and the engine's own files left out."""
    out = {}
    for p in sorted(work.rglob("*")):
        rel = p.relative_to(work).as_posix()
        if not p.is_file() or rel.startswith(".") or rel.startswith("report/") or p.name.endswith(".error.log") \
                or p.name == "stage.json":
            continue
        if p.suffix == ".exr":
            data = read_exr(p).tobytes()
        elif p.suffix == ".json" and p.name != "zarr.json":
            data = json.dumps(_json_content(json.loads(p.read_text())), sort_keys=True).encode()
        elif p.name == "zarr.json":
            data = json.dumps(_json_content(json.loads(p.read_text())), sort_keys=True).encode()
        else:
            data = p.read_bytes()
        out[rel] = hashlib.sha256(data).hexdigest()
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A tiny capture run once through every stage: (capture, content of its artifacts)."""
    cap = make_capture(tmp_path_factory.mktemp("ref") / "cap")
    assert main(["run", str(cap), "--quiet", *SETS]) == 0
    return cap, content(cap / "objcam")


def _copy(reference, tmp_path) -> Path:
    cap = tmp_path / "cap"
    shutil.copytree(reference[0], cap, symlinks=True)
    return cap


def _largest(folder: Path) -> Path:
    files = [p for p in folder.rglob("*") if p.is_file() and p.name != "stage.json"]
    return max(files, key=lambda p: p.stat().st_size)


def test_damaged_artifact_in_every_stage_is_rebuilt(reference, tmp_path):
    cap = _copy(reference, tmp_path)
    pipe_args = (cap, None, parse_overrides(["transport.env_height=8", "transport.model=direct"]))
    for i, stage in enumerate(STAGES):
        victim = _largest(cap / "objcam" / stage)
        if i % 2:
            victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])  # truncated
        else:
            victim.unlink()  # missing
        states = {r["stage"]: r["state"] for r in Pipeline(*pipe_args).status()}
        assert states[stage] == "damaged", (stage, states)
        reps = {r.stage: r for r in Pipeline(*pipe_args, quiet=True).run()}
        assert reps[stage].status == "ran" and reps[stage].summary.startswith("rebuilt: cached artifacts damaged")
        rel = victim.relative_to(cap / "objcam" / stage).as_posix()
        assert rel in reps[stage].summary
        assert all(r.status in ("cached", "n/a") for n, r in reps.items() if n != stage), reps
    assert content(cap / "objcam") == reference[1]


def _driver(cap: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "objcam.pipeline.cli", "run", str(cap), "--quiet", *SETS],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.mark.parametrize("stage,when", [("transport", "start"), ("solve", "file"), ("analysis", "file")])
def test_kill_9_inside_a_stage_resumes_to_the_same_artifacts(reference, tmp_path, stage, when):
    """Kill the run when the stage's temporary folder appears ("start") or when its first file appears in it
    ("file"); the rerun finishes with the reference's content and nothing half-written is left."""
    cap = _copy(reference, tmp_path)
    work = cap / "objcam"
    shutil.rmtree(work)
    proc = _driver(cap)
    deadline = time.time() + 120
    hit = False
    while time.time() < deadline and proc.poll() is None:
        tmps = list(work.glob(f".tmp-{stage}-*"))
        if tmps and (when == "start" or any(p.is_file() for t in tmps for p in t.rglob("*"))):
            proc.send_signal(signal.SIGKILL)
            hit = True
            break
        time.sleep(0.002)
    proc.wait()
    assert hit, f"the run never reached stage {stage} ({when})"
    assert not (work / stage / "stage.json").exists()
    assert main(["run", str(cap), "--quiet", *SETS]) == 0
    assert not list(work.glob(".tmp-*")) and not list(work.glob(".old-*"))
    assert content(work) == reference[1]


def test_comment_in_capture_toml_reruns_nothing(reference, tmp_path):
    cap = _copy(reference, tmp_path)
    toml = cap / "capture.toml"
    toml.write_text("# a note for the photographer\n" + toml.read_text().replace("[albedo]", "[albedo]  # grey"))
    reps = Pipeline(cap, overrides=parse_overrides(["transport.env_height=8", "transport.model=direct"]),
                    quiet=True).run()
    assert {r.status for r in reps} <= {"cached", "n/a"}
    toml.write_text(toml.read_text().replace("object = 0.5", "object = 0.4"))  # a real change still reruns
    reps = {r.stage: r.status for r in Pipeline(cap, overrides=parse_overrides(
        ["transport.env_height=8", "transport.model=direct"]), quiet=True).run(until="scene")}
    assert reps["scene"] == "ran"


def test_transport_size_is_checked_before_building(reference, tmp_path, capsys):
    cap = _copy(reference, tmp_path)
    t0 = time.perf_counter()
    code = main(["transport", str(cap), "--quiet", "--set", "transport.env_height=256"])
    err = capsys.readouterr().err.strip()
    # a support plane: A keeps the 129 rows of 512 texels above its horizon, a grey albedo one channel
    assert_one_line_error(code, err, "GiB", "transport.env_height", "66,048 texels")
    assert time.perf_counter() - t0 < 10
    rec = json.loads((reference[0] / "objcam" / "transport" / "stage.json").read_text())  # a build that fits
    # 192 px x 80 texels, one channel: A 61 kB + Gram 51 kB + the solve's 3 copies 154 kB, beside what it used
    assert rec["metrics"]["planned_peak_gib"] == round(266_240 / 2**30, 6) and rec["metrics"]["planned_seconds"] >= 0


@pytest.mark.parametrize("damage", ["malformed", "list", "nan_envmap"])
def test_bad_truth_is_a_user_error(reference, tmp_path, capsys, damage):
    cap = _copy(reference, tmp_path)
    (cap / "truth").mkdir()
    write_exr(cap / "truth" / "envmap.exr", np.ones((8, 16, 3), np.float32))
    meta = {"envmaps": {"t0": "truth/envmap.exr"}}
    if damage == "malformed":
        (cap / "truth" / "truth.json").write_text('{"envmaps": ')
    elif damage == "list":
        (cap / "truth" / "truth.json").write_text("[1, 2]")
    else:
        env = np.ones((8, 16, 3), np.float32)
        env[2, 3, 1] = np.nan
        write_exr(cap / "truth" / "envmap.exr", env)
        (cap / "truth" / "truth.json").write_text(json.dumps(meta))
    code = main(["evaluate", str(cap), "--quiet", *SETS])
    err = capsys.readouterr().err.strip()
    assert_one_line_error(code, err, "truth")
    assert "please report" not in err
