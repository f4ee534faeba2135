"""Building blocks of the self-contained report page: escaping, number formatting, PNG data URIs, figures,
tables and the page template (plain semantic HTML, a small inline stylesheet, no JavaScript, no external
resources)."""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

CSS = """
:root { color-scheme: light; }
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto; max-width: 1200px;
       padding: 1rem 1.5rem 3rem; color: #1b1b1b; background: #fff; line-height: 1.45; }
h1 { font-size: 1.6rem; margin-bottom: .2rem; }
h2 { font-size: 1.25rem; border-bottom: 1px solid #ddd; padding-bottom: .2rem; margin-top: 2rem; }
h3 { font-size: 1.05rem; margin-top: 1.4rem; }
code { font-family: ui-monospace, Menlo, Consolas, monospace; font-size: .92em; background: #f3f3f3;
       padding: 0 .2em; border-radius: 3px; word-break: break-all; }
.grid { display: grid; grid-template-columns: repeat(auto-fill, minmax(320px, 1fr)); gap: 1rem; }
.grid.wide { grid-template-columns: repeat(auto-fill, minmax(520px, 1fr)); }
figure { margin: 0; padding: .5rem; border: 1px solid #e3e3e3; border-radius: 6px; background: #fafafa; }
figure img { display: block; width: 100%; height: auto; image-rendering: pixelated; background: #222;
             outline: 1px solid #ccc; }
figure img.plot { image-rendering: auto; background: #fff; }
figcaption { font-size: .85rem; color: #444; margin-top: .35rem; }
.note { background: #fff8e1; border-left: 4px solid #f0b400; padding: .4rem .7rem; font-size: .9rem; }
.table-wrap { overflow-x: auto; }
table { border-collapse: collapse; font-size: .88rem; margin: .5rem 0 1rem; }
th, td { border: 1px solid #ddd; padding: .25rem .55rem; text-align: left; vertical-align: top;
         overflow-wrap: break-word; }
th { background: #f3f3f3; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
.meta { color: #555; font-size: .9rem; }
"""


def esc(value: Any) -> str:
    """Escape any value as HTML text (quotes included, so it is safe in attributes too)."""
    return html.escape(str(value), quote=True)


def fmt(value: Any) -> str:
    """How the page writes a value: floats with 4 significant digits, ints with thousands separators, None and
    non-finite numbers as an em dash / their name. Tests use this to find a metric in the page."""
    if value is None:
        return "\u2014"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v) for v in value)
    return str(value)


def png_data_uri(data: bytes) -> str:
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError("not a PNG")
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def read_png(path: Path, max_width: int | None = None) -> bytes | None:
    """The PNG's bytes, re-encoded smaller when it is wider than ``max_width``; None when missing or not a PNG."""
    path = Path(path)
    if not path.is_file():
        return None
    data = path.read_bytes()
    if not data.startswith(PNG_SIGNATURE):
        return None
    if max_width:
        import cv2
        import numpy as np

        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is not None and img.shape[1] > max_width:
            h = max(1, round(img.shape[0] * max_width / img.shape[1]))
            img = cv2.resize(img, (max_width, h), interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            if ok:
                data = buf.tobytes()
    return data


def figure(png: bytes | None, caption: str, alt: str | None = None, plot: bool = False,
           missing: str | None = None) -> str:
    """A <figure> with an inlined PNG and an escaped caption; a note in its place when ``png`` is None."""
    if png is None:
        return note(missing or f"not available: {caption}")
    cls = ' class="plot"' if plot else ""
    return (f'<figure><img{cls} src="{png_data_uri(png)}" alt="{esc(alt or caption)}">'
            f"<figcaption>{esc(caption)}</figcaption></figure>")


def note(text: str) -> str:
    return f'<p class="note">{esc(text)}</p>'


def grid(items: Iterable[str], wide: bool = False) -> str:
    items = [i for i in items if i]
    if not items:
        return ""
    return f'<div class="grid{" wide" if wide else ""}">' + "".join(items) + "</div>"


def table(headers: Sequence[str], rows: Iterable[Sequence[Any]], caption: str | None = None) -> str:
    """Table of escaped, formatted cells; numbers right-aligned."""
    out = ['<div class="table-wrap"><table>']
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    # a break opportunity after each underscore: long snake_case names wrap instead of widening the table
    out.append("<thead><tr>" + "".join(f'<th scope="col">{esc(h).replace("_", "_<wbr>")}</th>' for h in headers)
               + "</tr></thead><tbody>")
    for row in rows:
        cells = []
        for v in row:
            num = isinstance(v, (int, float)) and not isinstance(v, bool)
            cells.append(f'<td class="num">{esc(fmt(v))}</td>' if num else
                         f"<td>{esc(fmt(v)).replace('_', '_<wbr>')}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table></div>")
    return "".join(out)


def page(title: str, body: str, subtitle: str = "", css: str = "", script: str = "") -> str:
    """The page: ``css`` added to the stylesheet, ``script`` (a whole inline <script> element) at the end."""
    sub = f'<p class="meta">{subtitle}</p>' if subtitle else ""
    return ("<!DOCTYPE html>\n"
            '<html lang="en"><head><meta charset="utf-8">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{esc(title)}</title><style>{CSS}{css}</style></head>"
            f"<body><header><h1>{esc(title)}</h1>{sub}</header><main>{body}</main>"
            "<footer><p class=\"meta\">Written by objcam's report stage. Self-contained: every image is inlined."
            f"</p></footer>{script}</body></html>\n")
