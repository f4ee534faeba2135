"""Cache keys: a stage's key hashes its params, the contents of the capture files it reads, its upstream keys and
its own code, so an unchanged stage is skipped and any change reruns it and everything downstream."""

from __future__ import annotations

import hashlib
import importlib
import json
from pathlib import Path
from types import ModuleType

from pydantic import BaseModel

_CHUNK = 1 << 20


def file_digest(path: Path, memo: dict[str, list] | None = None) -> str:
    """sha256 of a file's bytes ("missing" if absent). ``memo`` maps path -> [size, mtime_ns, ctime_ns, inode,
    digest] so large unchanged inputs (raw photos) are hashed once. The ctime is in the key because a content change
    that keeps size and mtime (``touch -r``, a tool restoring times) still changes it, and nothing can set it back.
    Call it on regular files only (objcam.pipeline.inputs.check_input): a FIFO or device would never end."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        return "missing"
    key = str(path.resolve())
    stamp = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
    if memo is not None:
        hit = memo.get(key)
        if isinstance(hit, list) and len(hit) == 5 and hit[:4] == stamp:
            return hit[4]
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    digest = h.hexdigest()
    if memo is not None:
        memo[key] = stamp + [digest]
    return digest


def manifest_digest(path: Path) -> str:
    """Hash of capture.toml's parsed content, so a comment or a reformatting reruns nothing (its bytes' hash
    when it does not parse: the scene stage then reports why). The ``[params.<stage>]`` tables are left out: they
    reach each stage's key through its params, so a solve setting reruns solve, not the stages that read the
    capture's inputs."""
    import tomllib

    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return file_digest(path)
    data.pop("params", None)
    return "toml:" + hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


def _module_files(mod: ModuleType) -> list[Path]:
    f = Path(mod.__file__)
    if f.name == "__init__.py":  # a package: every module in it
        return sorted(f.parent.rglob("*.py"))
    return [f]


def code_digest(stage: ModuleType) -> str:
    """Hash of the stage module's source and of the objcam modules it declares in CODE_DEPS."""
    h = hashlib.sha256(str(getattr(stage, "VERSION", "")).encode())
    mods = [stage] + [importlib.import_module(m) for m in getattr(stage, "CODE_DEPS", ())]
    for mod in mods:
        for f in _module_files(mod):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def stage_key(name: str, code: str, params: BaseModel, inputs: dict[str, str], upstream: dict[str, str]) -> str:
    payload = {"stage": name, "code": code, "params": params.model_dump(mode="json"),
               "inputs": dict(sorted(inputs.items())), "upstream": dict(sorted(upstream.items()))}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]
