"""Issue 3's bad input, through the real CLI (``objcam ingest`` / ``objcam sfm``): each stops with exit status 2 and
ONE line that names the offending file (or folder) and the fix, writes nothing into the capture folder, leaves no
half-made stage folder, and the stage runs once the input is fixed.

Covered here (stage level; the readers' own unit tests are in tests/test_ingest.py, tests/test_sfm.py):
- a corrupt (zeroed data) or truncated raw, and a file that is not an image, among the views;
- a bracket mixing cameras through the CLI (tests/test_ingest_stage.py also covers sizes and a missing EXIF
  exposure, with the capture.toml fix);
- too few views for SfM, with a board and with [scale] only;
- SfM registering too few images (views that do not overlap).
The board not found in the views is tests/test_sfm_stage.py::test_wrong_board_is_one_line.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from objcam.capture.dng import write_dng
from tests.test_sfm import random_photos
from tests.test_ingest_stage import WB, block2, write_capture


def digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def run(stage: str, capture: Path, work: Path, capfd) -> tuple[int, str]:
    from objcam.pipeline.cli import main

    rc = main([stage, str(capture), "--work", str(work), "-q"])
    return rc, capfd.readouterr().err


def one_line(rc: int, err: str, *needles: str) -> str:
    assert rc == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one line, got:\n{err}"
    line = lines[0]
    assert line.startswith("objcam: error:") and "Traceback" not in err and "fix:" in line, line
    for n in needles:
        assert n.lower() in line.lower(), f"{n!r} not in {line!r}"
    return line


def _zeroed(data: bytes) -> bytes:
    """The DNG with a run of its pixel data zeroed (a card read error): samples far below the black level."""
    n = len(data)
    return data[: n // 2] + bytes(n // 4) + data[n // 2 + n // 4:]


@pytest.mark.parametrize("case", ["not_an_image", "not_a_jpeg", "truncated", "corrupt"])
def test_bad_view_file(tmp_path, capfd, case):
    cap = tmp_path / "cap"
    write_capture(cap, noise=None)
    view = cap / "views" / "v1.dng"
    good = view.read_bytes()
    if case.startswith("not_a"):  # notes saved under a photo's extension (no EXIF either: not reported as such)
        bad = cap / "views" / ("v2.dng" if case == "not_an_image" else "v2.jpg")
        bad.write_bytes(b"not a photo, just notes\n" * 40)
    else:
        bad = view
        bad.write_bytes(good[: len(good) // 3] if case == "truncated" else _zeroed(good))
    before = digest(cap)
    rc, err = run("ingest", cap, tmp_path / "w", capfd)
    line = one_line(rc, err, str(bad))
    assert {"not_an_image": "not an image", "not_a_jpeg": "not an image", "truncated": "truncated",
            "corrupt": "corrupt"}[case] in line, line
    assert "exposure" not in line, line
    assert digest(cap) == before  # the capture is untouched
    assert not (tmp_path / "w" / "ingest").exists()  # no half-written stage folder
    # fixed (the notes removed, the raw re-copied): the same command succeeds
    if case.startswith("not_a"):
        bad.unlink()
    else:
        view.write_bytes(good)
    rc, err = run("ingest", cap, tmp_path / "w", capfd)
    assert rc == 0, err
    assert (tmp_path / "w" / "ingest" / "views" / "v1.exr").is_file()


def test_bracket_from_two_cameras(tmp_path, capfd):
    cap = tmp_path / "cap"
    write_capture(cap, noise=None)
    frames = sorted((cap / "targets" / "t0").glob("*.dng"))
    keep = frames[3].read_bytes()
    write_dng(frames[3], np.full((80, 120, 3), 0.1), exposure_time=2.0 ** -4, wb=WB, make="Other", model="body")
    before = digest(cap)
    rc, err = run("ingest", cap, tmp_path / "w", capfd)
    one_line(rc, err, str(frames[3]), "bracket mixes cameras", frames[0].name, "one camera")
    assert digest(cap) == before and not (tmp_path / "w" / "ingest").exists()
    frames[3].write_bytes(keep)
    rc, err = run("ingest", cap, tmp_path / "w", capfd)
    assert rc == 0, err


@pytest.mark.parametrize("frame", ["scale", "board"])
def test_too_few_views(tmp_path, capfd, frame):
    """Two views: sfm stops before any SfM work, naming the views folder and how many to take."""
    cap = tmp_path / "cap"
    write_capture(cap, noise=None)
    if frame == "board":
        toml = cap / "capture.toml"
        toml.write_text(toml.read_text().replace("[scale]\nobject_height = 0.1\n", "[board]\n"))
    before = digest(cap)
    rc, err = run("sfm", cap, tmp_path / "w", capfd)
    one_line(rc, err, str(cap / "views"), "only 2 view(s)", "at least 6")
    assert digest(cap) == before
    assert (tmp_path / "w" / "ingest").is_dir() and not (tmp_path / "w" / "sfm").exists()


def test_sfm_registers_too_few(tmp_path, capfd):
    """Six views that do not overlap: SfM registers (almost) none; one line naming the views folder and the
    images that did not register, with the fix; rerunning gives the same answer and writes no sfm folder."""
    from objcam.image_io import write_exr

    cap = tmp_path / "cap"
    random_photos(cap / "views", 6, seed=5)  # photos that share nothing: no two overlap
    write_exr(cap / "targets" / "t0" / "t0.exr", np.full((240, 320, 3), 0.2, np.float32))
    times = ", ".join(f'"p{i:02d}.png" = 0.01' for i in range(6))
    (cap / "capture.toml").write_text(
        f'[scene]\nobject = "object.ply"\n\n[camera]\nexposure_times = {{ {times} }}\n\n[views]\n'
        'folder = "views"\nmax_size = 320\n\n[scale]\nobject_height = 0.1\n\n[[targets]]\nname = "t0"\n'
        'folder = "targets/t0"\n')
    before = digest(cap)
    for _ in range(2):
        rc, err = run("sfm", cap, tmp_path / "w", capfd)
        line = one_line(rc, err, str(cap / "views"), "registered", "more overlap")
        assert "registered none" in line or "(not: " in line, line
        assert digest(cap) == before and not (tmp_path / "w" / "sfm").exists()
