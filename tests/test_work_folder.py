"""Issue 24, the work folder: never written through a symbolic link (folder or lock), --work never adopts a
folder objcam did not make, damaged artifacts are rebuilt, a content change is seen even when size and mtime are
kept, and disk errors are one line. Uses test_pipeline's toy stages (the engine alone)."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest

from objcam.errors import ObjcamError
from objcam.pipeline.engine import Pipeline, parse_overrides
from tests.test_pipeline import runs, toy  # noqa: F401  (the fixture)


def test_lock_symlink_is_refused_and_its_target_untouched(toy, tmp_path):  # noqa: F811
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (toy / "objcam").mkdir()
    (toy / "objcam" / ".lock").symlink_to(victim)
    with pytest.raises(ObjcamError, match="lock file is a symbolic link"):
        Pipeline(toy).run()
    assert victim.read_text() == "precious"


def test_work_folder_symlink_is_refused(toy, tmp_path):  # noqa: F811
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / ".tmp-keep").mkdir(parents=True)
    (elsewhere / ".tmp-keep" / "data").write_text("mine")
    (toy / "objcam").symlink_to(elsewhere)
    with pytest.raises(ObjcamError, match="work folder is a symbolic link"):
        Pipeline(toy).run()
    with pytest.raises(ObjcamError, match="symbolic link"):
        Pipeline(toy, work=toy / "objcam").run()
    assert (elsewhere / ".tmp-keep" / "data").read_text() == "mine"
    assert sorted(p.name for p in elsewhere.iterdir()) == [".tmp-keep"]


def test_work_refuses_a_folder_objcam_did_not_make(toy, tmp_path):  # noqa: F811
    thesis = tmp_path / "U" / "report" / "thesis.txt"
    thesis.parent.mkdir(parents=True)
    thesis.write_text("chapter 1")
    with pytest.raises(ObjcamError, match="not empty and was not made by objcam"):
        Pipeline(toy, work=tmp_path / "U").run()
    assert thesis.read_text() == "chapter 1"
    new = tmp_path / "new"  # a new folder: made, marked, and accepted again on the next run
    assert len(Pipeline(toy, work=new).run()) == 3
    assert (new / ".objcam-work").is_file()  # objcam.pipeline.workdir.MARKER
    assert {r.status for r in Pipeline(toy, work=new).run()} == {"cached"}
    (new / ".objcam-work").unlink()  # a work folder of an older objcam (no marker) is known by its lock
    assert {r.status for r in Pipeline(toy, work=new).run()} == {"cached"}


@pytest.mark.parametrize("damage", ["truncate", "same_size_edit", "delete", "stage_json"])
def test_damaged_artifact_is_rebuilt_and_said(toy, damage):  # noqa: F811
    Pipeline(toy).run()
    f = toy / "objcam" / "first" / "value.txt"
    good = f.read_bytes()
    if damage == "truncate":
        f.write_bytes(good[:1])
    elif damage == "same_size_edit":
        st = f.stat()
        f.write_bytes(b"9" * len(good))
        os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))  # same size, same mtime
    elif damage == "delete":
        f.unlink()
    else:
        (toy / "objcam" / "first" / "stage.json").write_text("{")
    assert {r["stage"]: r["state"] for r in Pipeline(toy).status()}["first"] in (
        "damaged" if damage != "stage_json" else "missing",)
    reps = {r.stage: r for r in Pipeline(toy).run()}
    assert reps["first"].status == "ran"
    if damage != "stage_json":
        assert reps["first"].summary.startswith("rebuilt: cached artifacts damaged (value.txt")
    assert f.read_bytes() == good
    assert reps["second"].status == "cached" and reps["third"].status == "cached"  # same key: not rerun


def test_content_change_with_same_size_and_mtime_reruns(toy):  # noqa: F811
    Pipeline(toy).run()
    inp = toy / "input.txt"
    st = inp.stat()
    inp.write_text("4")  # same size as "3"
    os.utime(inp, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert {r["stage"]: r["state"] for r in Pipeline(toy).status()}["first"] == "stale"
    reps = {r.stage: r.status for r in Pipeline(toy).run()}
    assert reps["first"] == "ran"
    assert (toy / "objcam" / "first" / "value.txt").read_text() == "8.0"


@pytest.mark.parametrize("value", ["Infinity", "-Infinity", "NaN", "[1, NaN]"])
def test_non_finite_set_values_are_refused(value):
    with pytest.raises(ObjcamError, match="not a finite number"):
        parse_overrides([f"solve.ls={value}"])


def test_full_disk_is_one_line(toy, monkeypatch):  # noqa: F811
    mod = __import__("toystages.second", fromlist=["run"])

    def full(inputs, params):
        raise OSError(errno.ENOSPC, "No space left on device", str(inputs.out / "x"))

    monkeypatch.setattr(mod, "run", full)
    with pytest.raises(ObjcamError, match="the disk is full.*--work"):
        Pipeline(toy).run()
    assert not list((toy / "objcam").glob(".tmp-*"))


def test_read_only_capture_says_use_work(toy, monkeypatch):  # noqa: F811
    real_mkdir = Path.mkdir

    def ro_mkdir(self, *a, **k):  # root ignores permissions, so the read-only file system is simulated
        if self == toy / "objcam":
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return real_mkdir(self, *a, **k)

    monkeypatch.setattr(Path, "mkdir", ro_mkdir)
    with pytest.raises(ObjcamError, match="--work DIR"):
        Pipeline(toy).run()


def test_cli_disk_errors_are_one_line(toy, monkeypatch, capsys):  # noqa: F811
    from objcam.pipeline import cli

    def boom(self, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", "/x/.hashes.json")

    monkeypatch.setattr(Pipeline, "run", boom)
    assert cli.main(["run", str(toy), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "No space left" in err and "Traceback" not in err


@pytest.mark.timeout(60)
@pytest.mark.parametrize("plant", ["stage_fifo", "memo_fifo", "memo_dev_zero", "memo_not_a_dict"])
def test_planted_records_neither_hang_nor_mislead(toy, plant):  # noqa: F811
    """A capture sent with its objcam/ folder may hold FIFOs or links where objcam keeps its records."""
    work = toy / "objcam"
    (work / "first").mkdir(parents=True)
    if plant == "stage_fifo":
        os.mkfifo(work / "first" / "stage.json")
    elif plant == "memo_fifo":
        os.mkfifo(work / ".hashes.json")
    elif plant == "memo_dev_zero":
        (work / ".hashes.json").symlink_to("/dev/zero")
    else:
        (work / ".hashes.json").write_text('{"' + str((toy / "input.txt").resolve()) + '": 5}')
    reps = {r.stage: r.status for r in Pipeline(toy).run()}
    assert reps == {"first": "ran", "second": "ran", "third": "ran"}
    assert (work / "first" / "value.txt").read_text() == "6.0"


def test_a_stage_folder_that_is_a_link_is_replaced_not_followed(toy, tmp_path):  # noqa: F811
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "value.txt").write_text("forged")
    (toy / "objcam").mkdir()
    (toy / "objcam" / "first").symlink_to(elsewhere)
    reps = {r.stage: r.status for r in Pipeline(toy).run()}
    assert reps["first"] == "ran"
    assert not (toy / "objcam" / "first").is_symlink()
    assert (toy / "objcam" / "first" / "value.txt").read_text() == "6.0"
    assert (elsewhere / "value.txt").read_text() == "forged" and sorted(os.listdir(elsewhere)) == ["value.txt"]
