"""The report page in a real browser: headless Chromium (Debian's ``chromium``, installed by ``make setup``)
driven over the Chrome DevTools Protocol on a pipe (``--remote-debugging-pipe``: no driver binary, no Python
package, no network port). On the tiny synthetic capture of tests/test_report.py, run through the real CLI: the
page loads, every <img> decodes (naturalWidth > 0), nothing is logged at error level (console errors, uncaught
exceptions, failed loads: what chromedriver reports as SEVERE), and it loads in < 2 s of browser time and is
under 5 MB.

Measure any page (e.g. the demo's) with ``.venv/bin/python -m tests.test_report_browser PAGE.html``.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.test_report import capture  # noqa: F401  (the module fixture: a tiny capture run through the CLI)

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
LOAD_BUDGET_MS = 2000.0
SIZE_BUDGET = 5_000_000


def find_browser() -> str:
    """The Chromium executable; a test failure (never a skip) naming the fix when there is none."""
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    pytest.fail("headless Chromium not found (tried chromium, chromium-browser, google-chrome): run `make setup`, "
                "which installs Debian's chromium, or `apt-get install chromium`", pytrace=False)


class Browser:
    """Headless Chromium over CDP on a pipe: JSON messages, NUL-terminated, we write fd 3 and read fd 4."""

    def __init__(self, exe: str, timeout: float = 30.0):
        self.timeout = timeout
        self.profile = tempfile.mkdtemp(prefix="objcam-chromium-")
        to_chrome_r, self._w = os.pipe()
        self._r, from_chrome_w = os.pipe()

        def fds():  # in the child: the pipe ends as fds 3 and 4, kept across exec
            a, b = os.dup(to_chrome_r), os.dup(from_chrome_w)
            os.dup2(a, 3)
            os.dup2(b, 4)
            os.set_inheritable(3, True)
            os.set_inheritable(4, True)

        self.log = open(Path(self.profile) / "stderr.log", "wb")
        args = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                "--no-default-browser-check", "--remote-debugging-pipe", f"--user-data-dir={self.profile}",
                "about:blank"]
        self.proc = subprocess.Popen(args, close_fds=False, preexec_fn=fds, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=self.log)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf = b""
        self._id = 0
        self.events: list[dict] = []

    def _recv(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no answer from Chromium")
            ready, _, _ = select.select([self._r], [], [], left)
            if ready:
                chunk = os.read(self._r, 1 << 20)
                if not chunk:
                    tail = (Path(self.profile) / "stderr.log").read_bytes()[-600:].decode(errors="replace")
                    raise RuntimeError(f"Chromium closed the pipe; its stderr ends: {tail}")
                self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            m = self._recv(deadline)
            if m.get("id") == self._id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def wait_event(self, method: str) -> dict:
        deadline = time.monotonic() + self.timeout
        for m in self.events:
            if m.get("method") == method:
                return m
        while True:
            m = self._recv(deadline)
            self.events.append(m)
            if m.get("method") == method:
                return m

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except Exception:
            pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._w, self._r):
            try:
                os.close(fd)
            except OSError:
                pass
        self.log.close()
        shutil.rmtree(self.profile, ignore_errors=True)


PROBE = """JSON.stringify({
  images: Array.from(document.images).map(i => ({complete: i.complete, w: i.naturalWidth, alt: i.alt})),
  nav: performance.getEntriesByType('navigation')[0].toJSON(),
  title: document.title
})"""


def measure(page: Path, exe: str | None = None) -> dict:
    """Open ``page`` in headless Chromium and report: images (complete, naturalWidth, alt), errors (console
    errors, uncaught exceptions, error-level log entries), load_ms (navigation start to the end of the load
    event, browser time), dom_content_loaded_ms, bytes, title."""
    page = Path(page).resolve()
    b = Browser(exe or find_browser())
    try:
        target = b.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        s = b.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            b.call(f"{domain}.enable", session=s)
        nav = b.call("Page.navigate", {"url": page.as_uri()}, session=s)
        if nav.get("errorText"):
            raise RuntimeError(f"navigation failed: {nav['errorText']}")
        b.wait_event("Page.loadEventFired")
        res = b.call("Runtime.evaluate", {"expression": PROBE, "returnByValue": True}, session=s)
        info = json.loads(res["result"]["value"])
        errors = []
        for m in b.events:
            p = m.get("params", {})
            if m.get("method") == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                errors.append("console: " + " ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
            elif m.get("method") == "Runtime.exceptionThrown":
                d = p["exceptionDetails"]
                errors.append(f"exception: {d.get('text', '')} {d.get('exception', {}).get('description', '')}")
            elif m.get("method") == "Log.entryAdded" and p["entry"]["level"] == "error":
                errors.append(f"log ({p['entry']['source']}): {p['entry']['text']} {p['entry'].get('url', '')}")
    finally:
        b.close()
    nav = info["nav"]
    return {"images": info["images"], "errors": errors, "load_ms": float(nav["loadEventEnd"]),
            "dom_content_loaded_ms": float(nav["domContentLoadedEventEnd"]), "bytes": page.stat().st_size,
            "title": info["title"]}


LAYOUT = """JSON.stringify((function () {
  function box(e) { var r = e.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; }
  function overlaps(a, b) { return a[0] < b[2] - 0.5 && b[0] < a[2] - 0.5 && a[1] < b[3] - 0.5 && b[1] < a[3] - 0.5; }
  var clashes = [];
  document.querySelectorAll('.envaxis, .envbox').forEach(function (g) {
    var labels = Array.from(g.querySelectorAll(':scope > span')).map(function (s) { return [s.textContent, box(s)]; });
    for (var i = 0; i < labels.length; i++) for (var j = i + 1; j < labels.length; j++)
      if (overlaps(labels[i][1], labels[j][1])) clashes.push(labels[i][0] + ' / ' + labels[j][0]);
  });
  var wide = Array.from(document.querySelectorAll('.table-wrap, figure, section')).filter(function (e) {
    return e.scrollWidth > e.clientWidth + 1; }).map(function (e) { return e.className || e.id || e.tagName; });
  function level(c) { var d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data, s = 0;
    for (var i = 0; i < d.length; i += 4) s += d[i] + d[i + 1] + d[i + 2]; return s / (d.length / 4); }
  var canvases = Array.from(document.querySelectorAll('canvas.envmap'));
  var before = canvases.map(level);
  var slider = document.querySelector('input.exposure');
  var out = slider ? slider.parentNode.querySelector('output').textContent : null;
  if (slider) { slider.value = 2; slider.dispatchEvent(new Event('input')); }
  var after = canvases.map(level);
  return {scrollWidth: document.documentElement.scrollWidth, sections: Array.from(document.querySelectorAll(
    'section[id]')).map(function (s) { return [s.id, Math.round(s.getBoundingClientRect().top + scrollY)]; }),
    clashes: clashes, wide: wide, before: before, after: after, output: out,
    output_after: slider ? slider.parentNode.querySelector('output').textContent : null};
})())"""


def layout(page: Path, width: int = 1280, shots: Path | None = None, exe: str | None = None) -> dict:
    """Open ``page`` at ``width`` CSS pixels: the document's scroll width, each section's id and top, labels
    that overlap, elements wider than their box, the envmap canvases' mean level before and after moving the
    first exposure slider to +2 EV; with ``shots``, a screenshot of every section (shots/<id>.png)."""
    import base64

    b = Browser(exe or find_browser())
    try:
        target = b.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        s = b.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        b.call("Page.enable", session=s)
        b.call("Emulation.setDeviceMetricsOverride", {"width": width, "height": 900, "deviceScaleFactor": 1,
                                                      "mobile": False}, session=s)
        b.call("Page.navigate", {"url": Path(page).resolve().as_uri()}, session=s)
        b.wait_event("Page.loadEventFired")
        info = json.loads(b.call("Runtime.evaluate", {"expression": LAYOUT, "returnByValue": True},
                                 session=s)["result"]["value"])
        if shots is not None:
            shots.mkdir(parents=True, exist_ok=True)
            for sid, top in info["sections"]:
                shot = b.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True, "clip": {
                    "x": 0, "y": top, "width": width, "height": 900, "scale": 0.6}}, session=s)
                (shots / f"{sid}.png").write_bytes(base64.b64decode(shot["data"]))
    finally:
        b.close()
    return info


def test_report_page_in_headless_chromium(capture):  # noqa: F811
    page = capture / "objcam" / "report" / "index.html"
    exe = find_browser()
    m = measure(page, exe)
    print(f"\nreport in Chromium: {m['load_ms']:.0f} ms to load, {m['bytes'] / 1e6:.2f} MB, "
          f"{len(m['images'])} images (load average {os.getloadavg()[0]:.2f})")
    assert m["title"].startswith("objcam report")
    n_img = page.read_text(encoding="utf-8").count("<img ")
    assert len(m["images"]) == n_img >= 10
    missing = [i["alt"] for i in m["images"] if not (i["complete"] and i["w"] > 0)]
    assert not missing, f"images that did not decode: {missing}"
    assert not m["errors"], m["errors"]
    assert 0 < m["load_ms"] < LOAD_BUDGET_MS
    assert m["bytes"] < SIZE_BUDGET
    info = layout(page, 1280, exe=exe)  # nothing wider than a 1280 px window, no overlapping labels
    assert info["scrollWidth"] <= 1280 and not info["wide"] and not info["clashes"], info
    assert info["before"] and min(info["before"]) > 0  # the envmap canvases are drawn


def test_a_broken_page_is_caught(tmp_path):
    """The checks can fail: a missing image, a console error and a script exception are all reported."""
    page = tmp_path / "broken.html"
    page.write_text('<!DOCTYPE html><html><head><title>t</title></head><body><img src="nope.png" alt="gone">'
                    '<script>console.error("bad thing"); undefinedFunction();</script></body></html>')
    m = measure(page)
    assert [i["w"] for i in m["images"]] == [0]
    text = " | ".join(m["errors"])
    assert "bad thing" in text and "undefinedFunction" in text and "nope.png" in text


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        r = measure(Path(arg))
        bad = [i["alt"] for i in r["images"] if not (i["complete"] and i["w"] > 0)]
        print(json.dumps({"page": arg, "load_ms": round(r["load_ms"], 1),
                          "dom_content_loaded_ms": round(r["dom_content_loaded_ms"], 1), "bytes": r["bytes"],
                          "images": len(r["images"]), "missing_images": bad, "errors": r["errors"],
                          "load_average": os.getloadavg()[0]}, indent=2))
