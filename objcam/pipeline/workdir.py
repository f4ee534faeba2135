"""The work folder and its lock, made safe against what a capture (or a careless path) may hold: objcam never
follows a symbolic link for either, never adopts a non-empty folder it did not create, and says what to do when
the folder cannot be written (a read-only capture: use --work)."""

from __future__ import annotations

import errno
import fcntl
import os
import stat
from pathlib import Path

from objcam.errors import ObjcamError

MARKER = ".objcam-work"  # written into every work folder objcam creates or adopts
MARKER_TEXT = "objcam work folder: objcam may replace or delete anything in it\n"
LOCK = ".lock"
_READ_ONLY = (errno.EROFS, errno.EACCES, errno.EPERM)


def absolute(path: str | Path) -> Path:
    """An absolute path without resolving symbolic links (``Path.resolve`` would follow a linked work folder)."""
    return Path(os.path.abspath(os.fspath(path)))


def refuse_links(work: Path) -> None:
    """Refuse a work folder (or a lock, a stage folder inside it) that is a symbolic link or not a folder."""
    if work.is_symlink():
        raise ObjcamError("the work folder is a symbolic link; objcam never writes through one", work,
                          "remove the link (or give a real folder with --work DIR)")
    if work.exists() and not work.is_dir():
        raise ObjcamError("the work folder exists and is not a folder", work, "remove it or give --work DIR")


def prepare(work: Path, explicit: bool) -> None:
    """Create (or adopt) the work folder. ``explicit``: it was given with --work, so an existing non-empty folder
    without objcam's marker is refused (its files would be replaced or deleted)."""
    refuse_links(work)
    marker = work / MARKER
    # a folder from an objcam older than the marker is recognised by its lock file (every run makes one)
    ours = marker.is_file() or ((work / LOCK).is_file() and not (work / LOCK).is_symlink())
    if explicit and work.is_dir() and not ours and any(work.iterdir()):
        raise ObjcamError("--work names a folder that is not empty and was not made by objcam", work,
                          "give a new or empty folder (objcam replaces what is in its work folder)")
    try:
        work.mkdir(parents=True, exist_ok=True)
        refuse_links(work)  # a link may have appeared between the check and the mkdir
        if not marker.is_file() and not marker.is_symlink():
            with open(marker, "x") as f:
                f.write(MARKER_TEXT)
    except FileExistsError:
        pass
    except OSError as e:
        if e.errno in _READ_ONLY:
            raise ObjcamError(f"cannot write the work folder ({e.strerror})", work,
                              "give a writable artifact folder with --work DIR (e.g. for a read-only capture)") from None
        raise ObjcamError(f"cannot create the work folder ({e.strerror})", work, "give --work DIR") from None


def open_lock(work: Path) -> int:
    """Open the lock file without following a symlink (O_NOFOLLOW) and check it is a regular file."""
    path = work / LOCK
    flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise ObjcamError("the lock file is a symbolic link; objcam never writes through one", path,
                              "delete the link (objcam makes its own lock)") from None
        if e.errno in _READ_ONLY:
            raise ObjcamError(f"cannot write the lock file ({e.strerror})", path,
                              "give a writable artifact folder with --work DIR (e.g. for a read-only capture)") from None
        raise ObjcamError(f"cannot open the lock file ({e.strerror})", path, "delete it") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise ObjcamError("the lock file is not a regular file", path, "delete it (objcam makes its own lock)")
    return fd


def try_lock(fd: int) -> bool:
    """Take the exclusive lock without waiting; False when another process holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False


def read_holder(fd: int) -> str:
    """What the lock's holder wrote (``pid N``), read through our own descriptor (never by path)."""
    try:
        return os.pread(fd, 100, 0).decode(errors="replace").strip()
    except OSError:
        return ""
