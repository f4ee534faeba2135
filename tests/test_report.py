"""The report stage: one self-contained HTML page per capture (images inlined as PNG data URIs, no external
resources), on a tiny synthetic capture run through the real CLI with "report" added to the stage graph."""

from __future__ import annotations

import base64
import json
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from objcam.pipeline import graph
from objcam.pipeline.cli import main
from objcam.pipeline.stage import StageInputs
from objcam.report.html import PNG_SIGNATURE, fmt

VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}


class Checker(HTMLParser):
    """Balanced tags, every <img> a data: PNG, no external URL, and the visible text."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.images = 0
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        for k in ("src", "href"):
            v = a.get(k) or ""
            if "http://" in v or "https://" in v or v.startswith("//"):
                self.errors.append(f"external {k}: {v[:80]}")
        if tag == "img":
            self.images += 1
            src = a.get("src") or ""
            prefix = "data:image/png;base64,"
            if not src.startswith(prefix):
                self.errors.append(f"img src not a PNG data URI: {src[:60]}")
            elif not base64.b64decode(src[len(prefix):], validate=True).startswith(PNG_SIGNATURE):
                self.errors.append("img data is not a PNG")
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID:
            self.stack.pop()

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unbalanced </{tag}> (open: {self.stack[-3:]})")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def check_page(path: Path) -> tuple[Checker, str]:
    assert path.is_file()
    assert path.stat().st_size < 5_000_000
    text = path.read_text(encoding="utf-8")
    c = Checker()
    c.feed(text)
    c.close()
    assert not c.errors, c.errors[:5]
    assert not c.stack, c.stack
    return c, " ".join(c.text)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    cap = tmp_path_factory.mktemp("report") / "capture"
    assert main(["synth", str(cap), "--envmap", "sunrise", "--spp", "16",
                 "--cameras", '[{"width": 48, "height": 48, "distance": 0.3}]']) == 0
    assert "report" in graph.STAGES  # the last stage of `objcam run`
    assert main(["run", str(cap), "--quiet", "--set", "transport.model=direct"]) == 0
    return cap


def test_page_is_self_contained_and_complete(capture):
    work = capture / "objcam"
    c, text = check_page(work / "report" / "index.html")
    assert c.images >= 10  # overview, compare, target, prediction, residual, cooks, leverage, unc., spectrum, gains
    metrics = json.loads((work / "evaluate" / "metrics.json").read_text())["t0"]
    for k in ("ssim", "relative_rmse", "tonemapped_rmse", "brightest_angle_deg"):
        assert fmt(metrics[k]) in text, k
    assert f"row-mean map (no azimuth) scores SSIM {fmt(metrics['baselines']['row_mean']['ssim'])}" in text
    solve = json.loads((work / "solve" / "t0" / "solve.json").read_text())
    assert fmt(solve["kkt_residual_max"]) in text
    groups = json.loads((work / "analysis" / "analysis.json").read_text())["groups"]
    assert fmt(groups["cam0"]["effective_rank"]) in text
    for name in ("scene", "transport", "solve", "evaluate", "analysis"):
        info = json.loads((work / name / "stage.json").read_text())
        assert name in text and fmt(info["wall_seconds"]) in text, name
    assert "gamma 1/2.2" in text and str(capture) in text
    info = json.loads((work / "report" / "stage.json").read_text())
    assert info["metrics"]["bytes"] < 5_000_000


def test_no_truth_and_missing_artifacts_get_notes(capture, tmp_path):
    import objcam.stages.report as report

    work = tmp_path / "work"
    shutil.copytree(capture / "objcam", work, ignore=shutil.ignore_patterns("transport"))
    (work / "transport").mkdir()
    shutil.copy(capture / "objcam" / "transport" / "index.json", work / "transport" / "index.json")
    shutil.copy(capture / "objcam" / "transport" / "stage.json", work / "transport" / "stage.json")
    shutil.rmtree(work / "evaluate" / "t0")
    (work / "evaluate" / "metrics.json").write_text(json.dumps({"truth": False}))
    (work / "analysis" / "cam0" / "gains.png").unlink()
    (work / "solve" / "stage.json").unlink()
    out = tmp_path / "out"
    out.mkdir()
    res = report.run(StageInputs(capture=capture, upstream={n: work / n for n in report.DEPS}, out=out),
                     report.Params())
    _, text = check_page(out / "index.html")
    assert "no truth" in text.lower()
    assert "no gains.png" in text and "no stage.json" in text
    assert res.metrics["targets"] == 1


BENCH = {"transport": [{"setting": "direct K=4", "seconds": 5.0}, {"setting": "auto", "seconds": 20.0}],
         "solve": [{"setting": "direct K=4", "method": "exact", "hdri": "forest", "solve_s": 0.5, "ssim": 0.6,
                    "relative_rmse": 0.9},
                   {"setting": "auto", "method": "paper", "hdri": "city", "solve_s": 1.0, "ssim": 0.4,
                    "relative_rmse": 2.0},
                   {"setting": "missing A", "method": "exact", "hdri": "city", "solve_s": 1.0, "ssim": 0.4,
                    "relative_rmse": 2.0}]}


def test_bench_points_add_the_time_to_build_A():
    from objcam.report.speed import bench_points

    pts = bench_points(BENCH)
    assert [(p["label"], p["seconds"], p["ssim"]) for p in pts] == [("direct K=4 / exact", 5.5, 0.6),
                                                                    ("auto / paper", 21.0, 0.4)]


@pytest.fixture(scope="module")
def joint_capture(tmp_path_factory) -> Path:
    """Unknown support albedo, two illuminations: the joint solve writes an albedo the report must show."""
    root = tmp_path_factory.mktemp("report-joint")
    bench = root / "results.json"
    bench.write_text(json.dumps(BENCH))
    cap = root / "capture"
    assert main(["synth", str(cap), "--envmap", "sunrise", "--spp", "16", "--rotations-deg", "[0, 150]",
                 "--support-albedo", "dots", "--support-albedo-known", "false", "--texture-scale", "0.03",
                 "--cameras", '[{"width": 40, "height": 40, "distance": 0.3}]']) == 0
    assert main(["run", str(cap), "--quiet", "--set", "transport.model=direct", "--set", "transport.env_height=8",
                 "--set", f"report.bench_results={bench}"]) == 0
    return cap


def test_report_shows_albedo_and_speed_against_error(joint_capture):
    work = joint_capture / "objcam"
    c, text = check_page(work / "report" / "index.html")
    metrics = json.loads((work / "evaluate" / "metrics.json").read_text())
    for t in ("t0-rot000", "t0-rot150") if "t0-rot000" in metrics else metrics:
        m = metrics[t]
        assert (work / "solve" / t / "albedo.png").is_file()
        assert fmt(m["albedo_relative_rmse"]) in text and fmt(m["albedo_ssim"]) in text
    assert text.count("Recovered albedo") == len(metrics)
    assert "estimated albedo per pixel" in text and "true albedo | estimate" in text
    assert "Speed against error" in text and "benchmark: results.json (2 runs)" in text
    assert c.images >= 10 + 3 * len(metrics)


def test_envmap_viewer_exposure_is_the_scores_white():
    """The viewer's 0 EV is the white evaluate's PNGs and scores use (objcam.metrics.tonemap_scale): a dark room
    of uniform walls and two small lamps opens with its lamps at white, not as one flat white wall; a sky
    without a plateau keeps its 99th percentile."""
    from objcam.metrics import tonemap_scale
    from objcam.report.envmap_view import envmap_panel, reference

    room = np.full((16, 32, 3), 0.01)
    room[8:] = 0.0  # below the horizon: unsolved, written as 0
    room[3, 5] = 400.0
    room[5, 20] = 120.0
    walls = np.percentile(room[room > 0], 99)
    assert walls == pytest.approx(0.01)  # the plain percentile: the walls at white (the test of the test)
    assert reference(room) == pytest.approx(400.0)
    assert 'data-ref="400.0"' in envmap_panel("t", [("truth", room)])
    sky = np.linspace(0.1, 2.0, 16 * 32 * 3).reshape(16, 32, 3)
    assert reference(sky) == pytest.approx(tonemap_scale(sky)) == pytest.approx(np.percentile(sky, 99))
    assert reference(np.zeros((4, 8, 3))) == 1.0
    nan = room.copy()
    nan[0, 0] = np.nan
    assert reference(nan) == pytest.approx(400.0)
