"""Checks of a mesh file's own text before a loader sees it: pymeshlab silently drops vertices with NaN or
infinite coordinates (and the faces that use them), drops OBJ faces that index past the vertex list and reports a
PLY that does so as "Unable to open file". These read what the file declares, so the loader's result can be held
to it."""

from __future__ import annotations

import math
from pathlib import Path

MAX_SCAN_BYTES = 256 << 20  # text meshes larger than this are held to their declared counts only


def _finite(tokens: list[str]) -> bool:
    try:
        return all(math.isfinite(float(t)) for t in tokens)
    except ValueError:
        return False


def _scan_obj(lines: list[str]) -> tuple[str | None, int, int]:
    total = sum(1 for line in lines if line.split()[:1] == ["v"])  # positive indices may point forward
    nv = nf = 0
    for i, line in enumerate(lines, 1):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            if not _finite(parts[1:4]) or len(parts) < 4:
                return f"line {i}: vertex coordinates not finite numbers ({' '.join(parts[1:4])})", nv, nf
            nv += 1
        elif parts[0] == "f":
            for tok in parts[1:]:
                try:
                    idx = int(tok.split("/")[0])
                except ValueError:
                    return f"line {i}: face index {tok!r} is not a number", nv, nf
                if idx == 0 or idx > total or idx < -nv:
                    return f"line {i}: face index {idx} is past the vertex list ({total} vertices)", nv, nf
            nf += max(len(parts) - 3, 0)
    return None, nv, nf


def _scan_ply_ascii(lines: list[str]) -> tuple[str | None, int, int]:
    nv = nf = 0
    elements: list[tuple[str, int]] = []
    end = None
    for i, line in enumerate(lines):
        parts = line.split()
        if parts[:1] == ["element"] and len(parts) == 3:
            elements.append((parts[1], int(parts[2]) if parts[2].isdigit() else -1))
        if line.strip() == "end_header":
            end = i + 1
            break
    if end is None:
        return "no end_header line", 0, 0
    row = end
    for name, count in elements:
        if count < 0:
            return f"element {name} has no valid count", nv, nf
        body = lines[row: row + count]
        if len(body) < count:
            return f"declares {count} {name} elements but holds {len(body)}", nv, nf
        if name == "vertex":
            nv = count
            for k, line in enumerate(body):
                if not _finite(line.split()[:3]):
                    return f"vertex {k} has coordinates that are not finite numbers ({line.strip()[:60]})", nv, nf
        elif name == "face":
            nf = count
            for k, line in enumerate(body):
                parts = line.split()
                try:
                    n = int(parts[0])
                    idx = [int(t) for t in parts[1:1 + n]]
                except (ValueError, IndexError):
                    return f"face {k} is not a list of vertex indices", nv, nf
                bad = [j for j in idx if not 0 <= j < nv]
                if bad:
                    return f"face {k} uses vertex {bad[0]}, past the vertex list ({nv} vertices)", nv, nf
        row += count
    return None, nv, nf


def _ply_header_counts(head: bytes) -> tuple[int, int] | None:
    text = head.split(b"end_header", 1)[0].decode("ascii", errors="replace")
    counts = {}
    for line in text.splitlines():
        parts = line.split()
        if parts[:1] == ["element"] and len(parts) == 3 and parts[2].isdigit():
            counts[parts[1]] = int(parts[2])
    if "vertex" not in counts:
        return None
    return counts["vertex"], counts.get("face", 0)


def scan(path: Path) -> tuple[str | None, tuple[int, int] | None]:
    """(the first problem found in the file's text, or None; the (vertices, faces) it declares, or None when not
    known). Faces are counted as triangles where the file says how many corners each has."""
    path = Path(path)
    ext = path.suffix.lower()
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(4096)
    if ext == ".ply":
        declared = _ply_header_counts(head)
        if b"format ascii" not in head or size > MAX_SCAN_BYTES:
            return None, declared
        problem, nv, _ = _scan_ply_ascii(path.read_text(errors="replace").splitlines())
        return problem, declared
    if ext == ".obj" and size <= MAX_SCAN_BYTES:
        problem, nv, nf = _scan_obj(path.read_text(errors="replace").splitlines())
        return problem, (nv, nf)
    return None, None
