"""Generated captures for the fuzz test and bench (issue 24): valid, near-valid and hostile ones, and the check
that a run on each ends well.

``draw_capture(draw, sandbox)`` writes one capture into ``sandbox/cap`` from hypothesis draws: capture.toml with
mutated fields (paths that leave the capture, non-finite or out-of-range numbers, booleans, odd names, unknown
keys, garbage bytes), a mesh (valid, NaN or infinite vertices, faces past the vertex list, millimetres, floating,
garbage), a camera JSON (bad intrinsics, non-rigid poses, unknown keys), a target image (valid, noisy with
negatives, NaN, a hot pixel, 8-bit PNG, JPEG bytes named .exr, truncated, wrong size, a FIFO, /dev/zero) and
hostile work-folder contents (a linked lock, a linked work folder). ``sandbox/outside`` holds files a hostile
capture points at; nothing outside ``sandbox/cap/objcam`` may change.

``run_case(sandbox, argv)`` runs the CLI in this process under a timeout and returns an ``Outcome``: ``ok``
(exit 0, every artifact finite), ``refused`` (exit 2, one line naming a file) or a failure kind: ``traceback``,
``hang``, ``write_outside``, ``bad_message``, ``non_finite``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import stat
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from hypothesis import strategies as st

W, H = 16, 12
PARTS = ("mesh", "camera", "image", "toml", "work")
BASE_CAMERA = {"width": W, "height": H, "fx": 20.0, "fy": 20.0, "cx": (W - 1) / 2, "cy": (H - 1) / 2}

ODD_FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(
    [0.0, -0.0, 1e-9, -1.0, 1e9, 1e308, float("nan"), float("inf"), -float("inf")]))
ODD_VALUES = st.one_of(ODD_FLOATS, st.booleans(), st.integers(-10**12, 10**12), st.text(max_size=8),
                       st.lists(st.floats(allow_nan=True), max_size=4), st.none())


def _sphere(radius: float = 0.03, z: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    from objcam.synth.assets import icosphere

    v, f = icosphere(1)
    return v * radius + [0, 0, radius if z is None else z], f


def _ascii_ply(v: list, f: list) -> str:
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    return head + "".join(" ".join(str(x) for x in p) + "\n" for p in v) + "".join(
        f"{len(t)} " + " ".join(str(i) for i in t) + "\n" for t in f)


def _kind(draw, bad: bool, kinds: list[str]) -> str:
    """'valid', or one of ``kinds`` when this part of the capture is the one made bad."""
    return draw(st.sampled_from(kinds)) if bad else "valid"


def _camera(draw, bad: bool) -> dict:
    from objcam.camera import look_at

    eye = draw(st.sampled_from([[0.3, 0.0, 0.25], [0.0, 0.3, 0.3], [-0.2, -0.2, 0.2], [0.05, 0.0, 0.5]]))
    cam = dict(BASE_CAMERA, world_from_camera=look_at(np.array(eye), np.zeros(3)).tolist())
    kind = _kind(draw, bad, ["field", "pose", "extra", "drop", "garbage", "look_away"])
    if kind == "look_away":
        cam["world_from_camera"] = look_at(np.array([3.0, 0.0, 0.25]), np.array([6.0, 0.0, 0.0])).tolist()
    if kind == "field":
        cam[draw(st.sampled_from(["width", "height", "fx", "fy", "cx", "cy"]))] = draw(ODD_VALUES)
    elif kind == "pose":
        m = np.asarray(cam["world_from_camera"])
        i, j = draw(st.integers(0, 3)), draw(st.integers(0, 3))
        m[i, j] = draw(ODD_FLOATS)
        cam["world_from_camera"] = m.tolist()
    elif kind == "extra":
        cam[draw(st.text(min_size=1, max_size=6))] = draw(ODD_VALUES)
    elif kind == "drop":
        cam.pop(draw(st.sampled_from(sorted(cam))))
    elif kind == "garbage":
        return {"__raw__": draw(st.binary(max_size=64))}
    return cam


def _image(draw, path: Path, sandbox: Path, bad: bool) -> None:
    import cv2

    from objcam.image_io import write_exr

    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    img = (0.3 + 0.01 * rng.normal(size=(H, W, 3))).astype(np.float32)
    kind = _kind(draw, bad, ["noise_neg", "nan", "hot", "offset", "png8", "jpeg_as_exr", "truncated", "size",
                             "channels", "empty", "garbage", "fifo", "dev_zero", "outside_link", "folder",
                             "huge_values"])
    if kind == "noise_neg":
        img = (0.01 + 0.01 * rng.normal(size=(H, W, 3))).astype(np.float32)
    elif kind == "nan":
        img[rng.integers(H), rng.integers(W), rng.integers(3)] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    elif kind == "hot":
        img[rng.integers(H), rng.integers(W)] = draw(st.floats(1e3, 1e30))
    elif kind == "offset":
        img -= draw(st.floats(0.0, 2.0))
    elif kind == "huge_values":
        img *= draw(st.floats(1e-30, 1e30))
    elif kind == "size":
        img = np.zeros((draw(st.integers(1, 20)), draw(st.integers(1, 20)), 3), np.float32)
    elif kind == "channels":
        img = img[..., : draw(st.sampled_from([1, 2]))] if draw(st.booleans()) else np.concatenate([img, img], 2)
    if kind == "png8":
        cv2.imwrite(str(path.with_suffix(".png")), (np.clip(img, 0, 1) * 255).astype(np.uint8))
        os.replace(path.with_suffix(".png"), path)
    elif kind == "jpeg_as_exr":
        path.write_bytes(cv2.imencode(".jpg", (np.clip(img, 0, 1) * 255).astype(np.uint8))[1].tobytes())
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "garbage":
        path.write_bytes(draw(st.binary(max_size=256)))
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "dev_zero":
        path.symlink_to("/dev/zero")
    elif kind == "outside_link":
        path.symlink_to(sandbox / "outside" / "image.exr")
    elif kind == "folder":
        path.mkdir()
    else:
        write_exr(path, img)
        if kind == "truncated":
            data = path.read_bytes()
            path.write_bytes(data[: draw(st.integers(0, len(data) - 1))])


def _mesh(draw, cap: Path, sandbox: Path, bad: bool) -> str:
    from objcam.synth.assets import write_ply

    v, f = _sphere()
    kind = _kind(draw, bad, ["nan", "bad_index", "mm", "floating", "garbage", "empty", "obj", "obj_bad",
                             "no_faces", "outside", "absolute", "missing", "dev_zero", "folder"])
    name = "object.ply"
    if kind in ("valid", "mm", "floating"):
        if kind == "mm":
            v = v * 1000
        if kind == "floating":
            v = v + [0, 0, draw(st.floats(0.01, 10))]
        write_ply(cap / name, v, f)
    elif kind == "nan":
        vv = v.tolist()
        vv[draw(st.integers(0, len(vv) - 1))][draw(st.integers(0, 2))] = draw(st.sampled_from(["nan", "inf", "-inf"]))
        (cap / name).write_text(_ascii_ply(vv, f.tolist()))
    elif kind == "bad_index":
        ff = f.tolist()
        ff[draw(st.integers(0, len(ff) - 1))][draw(st.integers(0, 2))] = draw(
            st.one_of(st.integers(len(v), 10**9), st.integers(-10**9, -1)))
        (cap / name).write_text(_ascii_ply(v.tolist(), ff))
    elif kind == "garbage":
        (cap / name).write_bytes(draw(st.binary(max_size=256)))
    elif kind == "empty":
        (cap / name).write_bytes(b"")
    elif kind in ("obj", "obj_bad"):
        name = "object.obj"
        lines = [f"v {' '.join(map(str, p))}" for p in v] + [f"f {' '.join(str(i + 1) for i in t)}" for t in f]
        if kind == "obj_bad":
            lines[draw(st.integers(0, len(lines) - 1))] = draw(st.sampled_from(
                ["v nan 0 0", "v 0 inf 0", "f 1 2 99999", "f 0 1 2", "f a b c", "v 1", "f -99999 1 2"]))
        (cap / name).write_text("\n".join(lines) + "\n")
    elif kind == "no_faces":
        (cap / name).write_text(_ascii_ply(v.tolist()[:3], []))
    elif kind == "outside":
        name = "../outside/object.ply"
    elif kind == "absolute":
        name = str(sandbox / "outside" / "object.ply")
    elif kind == "missing":
        name = "nothing.ply"
    elif kind == "dev_zero":
        (cap / name).symlink_to("/dev/zero")
    elif kind == "folder":
        (cap / name).mkdir()
    return name


def _toml_value(v: Any) -> str:
    """A TOML literal for ``v`` (json's spelling works for strings, numbers and arrays; TOML's for the rest)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v == float("inf") else "-inf" if v == -float("inf") else repr(v))
    if v is None:
        return '""'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return json.dumps(v)


def draw_capture(draw: Callable, sandbox: Path) -> dict:
    """Write one generated capture into ``sandbox/cap``; returns the recipe's kinds (for counting)."""
    from objcam.image_io import write_exr
    from objcam.synth.assets import write_ply

    cap = sandbox / "cap"
    (cap / "targets").mkdir(parents=True)
    out = sandbox / "outside"
    out.mkdir()
    (out / "secret.txt").write_text("do not touch")
    v, f = _sphere()
    write_ply(out / "object.ply", v, f)
    write_exr(out / "image.exr", np.full((H, W, 3), 0.3, np.float32))

    # most captures have one bad part (near-valid), some two, a quarter none (valid)
    bad = draw(st.one_of(st.just(frozenset()), st.frozensets(st.sampled_from(PARTS), min_size=1, max_size=2)))
    obj = _mesh(draw, cap, sandbox, "mesh" in bad)
    cam = _camera(draw, "camera" in bad)
    if "__raw__" in cam:
        (cap / "targets" / "t0.json").write_bytes(cam["__raw__"])
    else:
        (cap / "targets" / "t0.json").write_text(json.dumps(cam))
    _image(draw, cap / "targets" / "t0.exr", sandbox, "image" in bad)

    scene = {"object": obj}
    albedo: dict[str, Any] = {"object": 0.5, "support": [0.6, 0.6, 0.6]}
    target: dict[str, Any] = {"name": "t0", "image": "targets/t0.exr", "camera": "targets/t0.json"}
    kind = _kind(draw, "toml" in bad, ["scene", "albedo", "target", "extra", "name", "garbage", "image_path",
                                       "mask", "comment"])
    if kind == "scene":
        scene[draw(st.sampled_from(["plane_size", "support"]))] = draw(ODD_VALUES)
    elif kind == "albedo":
        albedo[draw(st.sampled_from(["object", "support"]))] = draw(ODD_VALUES)
    elif kind == "target":
        target[draw(st.sampled_from(["noise_sigma", "saturation", "radiometry", "illumination", "encoding"]))] = \
            draw(ODD_VALUES)
    elif kind == "extra":
        target[draw(st.sampled_from(["colour", "exposure", "gain"]))] = 1.0
    elif kind == "name":
        target["name"] = draw(st.one_of(st.sampled_from([".", "..", "", "a/b", "../x", "t 0", "CON", "a" * 300]),
                                        st.text(max_size=12)))
    elif kind == "image_path":
        target["image"] = draw(st.sampled_from(["../outside/image.exr", str(out / "image.exr"), "targets",
                                                "targets/none.exr", "/dev/zero", "", "/"]))
    elif kind == "mask":
        (cap / "targets" / "m.png").write_bytes(draw(st.binary(max_size=64)))
        target["mask"] = "targets/m.png"
    lines = ["[scene]"] + [f"{k} = {_toml_value(x)}" for k, x in scene.items()]
    lines += ["", "[albedo]"] + [f"{k} = {_toml_value(x)}" for k, x in albedo.items()]
    lines += ["", "[[targets]]"] + [f"{k} = {_toml_value(x)}" for k, x in target.items()]
    text = "\n".join(lines) + "\n"
    if kind == "comment":
        text = "# written by hand\n" + text.replace("[albedo]", "[albedo]  # grey card")
    if kind == "garbage":
        raw = bytearray(text.encode())
        for _ in range(draw(st.integers(1, 4))):
            raw[draw(st.integers(0, len(raw) - 1))] = draw(st.integers(0, 255))
        (cap / "capture.toml").write_bytes(bytes(raw))
    else:
        (cap / "capture.toml").write_text(text)

    work = _kind(draw, "work" in bad, ["lock_link", "work_link", "tmp_link", "old_link", "lock_fifo", "stage_fifo",
                                       "memo_fifo", "memo_link", "memo_garbage", "stage_link"])
    if work in ("stage_fifo", "memo_fifo", "memo_link", "memo_garbage"):
        (cap / "objcam" / "scene").mkdir(parents=True)
        if work == "stage_fifo":
            os.mkfifo(cap / "objcam" / "scene" / "stage.json")
        elif work == "memo_fifo":
            os.mkfifo(cap / "objcam" / ".hashes.json")
        elif work == "memo_link":
            (cap / "objcam" / ".hashes.json").symlink_to("/dev/zero")
        else:
            (cap / "objcam" / ".hashes.json").write_text(draw(st.sampled_from(['{"a": 5}', "[1]", '{"x": [1, 2]}',
                                                                              "nan", "{"])))
    elif work == "stage_link":
        (cap / "objcam").mkdir()
        (cap / "objcam" / "scene").symlink_to(out)
    elif work == "lock_fifo":
        (cap / "objcam").mkdir()
        os.mkfifo(cap / "objcam" / ".lock")
    elif work == "lock_link":
        (cap / "objcam").mkdir()
        (cap / "objcam" / ".lock").symlink_to(out / "secret.txt")
    elif work == "work_link":
        (cap / "objcam").symlink_to(out)
    elif work in ("tmp_link", "old_link"):
        (cap / "objcam").mkdir()
        (cap / "objcam" / (".tmp-scene-x" if work == "tmp_link" else ".old-scene-x")).symlink_to(out)
    return {"bad": sorted(bad), "mesh": obj, "toml": kind, "work": work}


@dataclass
class Outcome:
    kind: str  # ok | refused | traceback | hang | write_outside | bad_message | non_finite
    code: int | None
    message: str


def _snapshot(root: Path, skip: Path) -> dict[str, tuple]:
    """Every entry under ``root`` except ``skip``'s subtree: (type, size, content hash) without following links."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        d = Path(dirpath)
        if d == skip or skip in d.parents:
            dirnames[:] = []
            continue
        for name in dirnames + filenames:
            p = d / name
            if p == skip:
                continue
            st_ = os.lstat(p)
            if stat.S_ISLNK(st_.st_mode):
                out[str(p)] = ("link", os.readlink(p))
            elif stat.S_ISREG(st_.st_mode):
                out[str(p)] = ("file", st_.st_size, hashlib.sha256(p.read_bytes()).hexdigest())
            else:
                out[str(p)] = ("other", stat.S_IFMT(st_.st_mode))
    return out


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


def _finite_artifacts(work: Path) -> str | None:
    from objcam.image_io import read_exr

    for p in sorted(work.rglob("*")):
        if p.is_symlink() or not p.is_file():
            continue
        if p.suffix == ".exr" and not np.all(np.isfinite(read_exr(p))):
            return str(p)
        if p.suffix == ".npz":
            with np.load(p) as z:
                if any(z[k].dtype.kind == "f" and not np.all(np.isfinite(z[k])) for k in z.files):
                    return str(p)
    return None


def run_case(sandbox: Path, argv: list[str], timeout_s: int = 60) -> Outcome:
    """Run ``objcam ARGV`` on ``sandbox/cap`` in this process and judge how it ended (see the module docstring)."""
    from objcam.pipeline.cli import main

    cap = sandbox / "cap"
    work = cap / "objcam"
    before = _snapshot(sandbox, work)
    err = io.StringIO()
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(timeout_s)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main([argv[0], str(cap), "--quiet", *argv[1:]])
    except _Hang:
        return Outcome("hang", None, f"no answer in {timeout_s} s")
    except SystemExit as e:  # argparse
        code = int(e.code or 0)
    except BaseException:  # noqa: BLE001 - any escape is the defect being counted
        return Outcome("traceback", None, traceback.format_exc(limit=-3))
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    after = _snapshot(sandbox, work)
    if before != after:
        changed = sorted(set(before.items()) ^ set(after.items()))
        return Outcome("write_outside", code, str(changed[:3]))
    msg = err.getvalue().strip()
    if code == 0:
        bad = _finite_artifacts(work) if work.is_dir() and not work.is_symlink() else None
        return Outcome("non_finite", code, bad) if bad else Outcome("ok", 0, "")
    lines = msg.splitlines()
    if code != 2 or len(lines) != 1 or "Traceback" in msg or "please report" in msg \
            or not lines[0].startswith("objcam: error: ") or ("/" not in lines[0] and "--set" not in lines[0]):
        return Outcome("bad_message", code, msg[-400:])
    return Outcome("refused", 2, lines[0])
