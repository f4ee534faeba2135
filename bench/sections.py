"""bench/results.md is shared by every benchmark: each owns one generated block and replaces only that one.

A benchmark's block sits between ``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->``, inside a ``## `` section
whose other text (what the numbers mean, what was tried) is written by hand and kept. Rerunning one benchmark
leaves the others' numbers and every note as they were.
"""

from __future__ import annotations

from pathlib import Path

RESULTS = Path("bench/results.md")
HEADER = ("# objcam benchmark: speed against error\n\n"
          "Each block between `bench:` markers is written by one benchmark (`make bench` runs them all, "
          "`make bench BENCH=\"core analysis\"` some); the text around the blocks is written by hand.\n")


def write_section(name: str, body: str, title: str, path: Path = RESULTS) -> None:
    """Replace benchmark ``name``'s block in ``path`` with ``body`` (markdown); a missing block is appended as a
    new section ``## {title}``. Written atomically."""
    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    block = f"{begin}\n{body.strip()}\n{end}"
    text = path.read_text() if path.is_file() else HEADER
    i, j = text.find(begin), text.find(end)
    if i >= 0 and j > i:
        text = text[:i] + block + text[j + len(end):]
    else:
        text = text.rstrip("\n") + f"\n\n## {title}\n\n{block}\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def invocation(module: str, argv: list[str] | None) -> str:
    """How a block was made, for its first line: ``python -m MODULE ARGS`` (``--write`` left out)."""
    import sys
    import time

    args = [a for a in (sys.argv[1:] if argv is None else argv) if a != "--write"]
    return f"`python -m {' '.join([module, *args])}`, {time.strftime('%Y-%m-%d')}"
