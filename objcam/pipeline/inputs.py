"""The gate every capture input passes before a stage reads it: a regular file (never a folder, FIFO or device,
which would hang the content hash), inside the capture folder unless the user allows otherwise, and holding what
its extension says (an EXR that is really a JPEG is refused here, not decoded as something else)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from objcam.errors import InputError

# The first bytes of each format objcam reads, by extension (lower case). Formats not listed are not sniffed.
MAGIC: dict[str, tuple[bytes, ...]] = {
    ".exr": (b"\x76\x2f\x31\x01",),
    ".png": (b"\x89PNG\r\n\x1a\n",),
    ".jpg": (b"\xff\xd8\xff",),
    ".jpeg": (b"\xff\xd8\xff",),
    ".tif": (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),
    ".tiff": (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),
    ".dng": (b"II*\x00", b"MM\x00*"),
    ".pfm": (b"PF", b"Pf"),
    ".hdr": (b"#?",),
    ".stl": (),  # ASCII ("solid") or binary (any header): not sniffable
    ".ply": (b"ply",),
    ".json": (),
}
_IMAGES = {".exr", ".png", ".jpg", ".jpeg", ".tif", ".tiff", ".dng", ".pfm", ".hdr"}
_ASCII_FIRST = {".json", ".toml", ".obj", ".off"}  # text formats: a NUL byte in the head means binary junk

ALLOW_OUTSIDE_FIX = "move it into the capture folder, or pass --allow-outside-inputs to read it where it is"


def inside(path: Path, root: Path) -> bool:
    """True when ``path`` (symlinks resolved) lies inside ``root`` (resolved)."""
    try:
        Path(os.path.realpath(path)).relative_to(os.path.realpath(root))
        return True
    except ValueError:
        return False


def check_input(path: Path, capture: Path, allow_outside: bool = False) -> bool:
    """Raise InputError unless ``path`` is a usable input of ``capture``; False when it does not exist (the stage
    then reports it missing in its own words), True otherwise."""
    path = Path(path)
    if not allow_outside and not inside(path, capture):
        how = "is a symbolic link to a file" if inside(os.path.abspath(path), capture) else "lies"
        raise InputError(f"input {how} outside the capture folder {capture}", path, ALLOW_OUTSIDE_FIX)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    except OSError as e:  # a symlink loop, a path through a file, no permission
        raise InputError(f"input cannot be read ({e.strerror})", path, "give a readable file") from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO, socket or device)"
        raise InputError(f"input is {kind}", path, "give a regular file")
    if not os.access(path, os.R_OK):
        raise InputError("input is not readable (permission denied)", path, "make it readable")
    sniff(path)
    return True


def sniff(path: Path) -> None:
    """Refuse a file whose first bytes contradict its extension (e.g. JPEG bytes named .exr)."""
    ext = path.suffix.lower()
    magics = MAGIC.get(ext)
    if not magics and ext not in _ASCII_FIRST:
        return
    with open(path, "rb") as f:
        head = f.read(64)
    if not head:
        raise InputError("input file is empty", path, "re-export it")
    if magics and not any(head.startswith(m) for m in magics):
        found = next((e for e, ms in MAGIC.items() if ms and any(head.startswith(m) for m in ms)), None)
        what = (f"its content is {found[1:].upper()}" if found else "it is not an image in that format"
                if ext in _IMAGES else "its content is not that format")
        raise InputError(f"file is named {ext} but {what}", path,
                         f"convert it to a real {ext[1:].upper()} file (or give it its true extension)")
    if ext in _ASCII_FIRST and b"\x00" in head:
        raise InputError(f"file is named {ext} but holds binary data", path, "give the text file")
