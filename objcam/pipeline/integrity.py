"""Artifact integrity: every finished stage records the size and content hash of each file it wrote
(``stage.json`` ``artifacts``); before a stage is skipped its files are checked against that record, so a
truncated, edited or deleted artifact is rebuilt instead of trusted. Hashes are memoised by (size, mtime, ctime,
inode), so an unchanged artifact costs one ``stat``: any write to a file changes its ctime, which no tool can set
back."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from objcam.pipeline.cache import file_digest

RECORD = "stage.json"


def artifact_files(folder: Path) -> list[Path]:
    """Every regular file under ``folder`` except the stage record, sorted."""
    return sorted(p for p in Path(folder).rglob("*") if p.is_file() and not p.is_symlink()
                  and p.relative_to(folder).as_posix() != RECORD)


def record_artifacts(folder: Path, memo: dict[str, list] | None = None) -> dict[str, list]:
    """{relative path: [size in bytes, sha256]} of a finished stage's files."""
    out = {}
    for p in artifact_files(folder):
        out[p.relative_to(folder).as_posix()] = [p.stat().st_size, file_digest(p, memo)]
    return out


def remember(folder: Path, artifacts: dict[str, list], memo: dict[str, list]) -> None:
    """Seed the hash memo with a just-installed stage's files (their paths changed when the folder was renamed)."""
    for rel, (_, digest) in artifacts.items():
        p = folder / rel
        try:
            st = p.stat()
        except OSError:
            continue
        memo[str(p.resolve())] = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, digest]


def damage(folder: Path, artifacts: dict[str, list] | None, memo: dict[str, list] | None = None) -> str | None:
    """None when every recorded artifact is present with its size and hash, else what is wrong (one phrase)."""
    if artifacts is None:
        return "its record lists no artifacts (written by an older objcam)"
    for rel, (size, digest) in sorted(artifacts.items()):
        p = Path(folder) / rel
        try:
            st = os.lstat(p)
        except OSError:
            return f"{rel} is missing"
        if not stat.S_ISREG(st.st_mode):
            return f"{rel} is not a regular file"
        if st.st_size != size:
            return f"{rel} is {st.st_size:,} bytes, {size:,} when written"
        if file_digest(p, memo) != digest:
            return f"{rel}'s content changed since it was written"
    return None
