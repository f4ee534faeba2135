"""User-facing errors: one line that names the file and says how to fix it."""

from __future__ import annotations

from pathlib import Path


class ObjcamError(Exception):
    """An error the user can fix. The CLI prints ``str(err)`` on one line and exits with status 2."""

    def __init__(self, message: str, path: str | Path | None = None, fix: str | None = None):
        self.path = Path(path) if path is not None else None
        self.fix = fix
        parts = [f"{self.path}: {message}" if self.path is not None else message]
        if fix:
            parts.append(f"fix: {fix}")
        super().__init__(one_line(" -- ".join(parts)))


def one_line(text: str) -> str:
    """``text`` on one printable line: line breaks of every kind and control characters (a capture's names and
    keys may hold any, terminal escapes included) become spaces."""
    return "".join(ch if ch.isprintable() else " " for ch in " ".join(text.splitlines()))


class InputError(ObjcamError):
    """A capture input (manifest, mesh, image, camera) is missing or malformed."""


class StageError(ObjcamError):
    """A stage could not produce a trustworthy result from valid inputs."""
