"""Speed against error: where this capture's run sits among the benchmark's settings.

The benchmark (``make bench``) writes ``results.json`` with, per transport setting, the time to build A, and per
(setting, solve method, HDRI) the solve time and the envmap metrics. The figure plots total time (A + solve, log
scale) against SSIM and against relative RMSE, one marker per solve method and one colour per HDRI, and overlays
this capture's targets (transport + solve wall time of the run, the evaluate stage's metrics) as black stars.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

# The benchmark's results: the copy shipped in the package (``make bench`` refreshes it beside bench/results.json,
# so an installed objcam has it too), then a source checkout's latest local run.
DEFAULT_RESULTS = (Path(__file__).resolve().parents[1] / "assets" / "bench_results.json",
                   Path(__file__).resolve().parents[2] / "bench" / "out" / "results.json")


def find_bench_results(path: str | Path | None = None) -> Path | None:
    """``path`` if given and present, else the first default that exists, else None."""
    if path is not None:
        p = Path(path)
        return p if p.is_file() else None
    return next((p for p in DEFAULT_RESULTS if p.is_file()), None)


def bench_points(results: dict) -> list[dict[str, Any]]:
    """One point per solve row: {'label', 'method', 'hdri', 'seconds', 'ssim', 'relative_rmse'}; rows without
    a transport time or metrics are skipped."""
    a_time = {t["setting"]: t.get("seconds") for t in results.get("transport", []) if isinstance(t, dict)}
    out = []
    for s in results.get("solve", []):
        if not isinstance(s, dict):
            continue
        ta, ts = a_time.get(s.get("setting")), s.get("solve_s")
        if ta is None or ts is None or s.get("ssim") is None or s.get("relative_rmse") is None:
            continue
        out.append({"label": f"{s['setting']} / {s.get('method')}", "method": str(s.get("method")),
                    "hdri": str(s.get("hdri")), "seconds": float(ta) + float(ts), "ssim": float(s["ssim"]),
                    "relative_rmse": float(s["relative_rmse"])})
    return out


def _log_ticks(axis) -> None:
    """Plain-number labels on a log axis at 1, 2, 5 x 10^k (1 x 10^k only past two decades), none on the minor
    ticks: matplotlib labels minor ticks when the range is under a decade, and those labels overlap."""
    import math

    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    lo, hi = sorted(axis.get_view_interval())
    decades = math.log10(hi / lo) if lo > 0 and hi > 0 else 3.0
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0) if decades <= 2 else (1.0,)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_locator(LogLocator(base=10, subs=tuple(range(2, 10))))
    axis.set_minor_formatter(NullFormatter())


def speed_error_png(points: list[dict[str, Any]], capture_points: list[dict[str, Any]], dpi: int = 100) -> bytes:
    """PNG bytes of the two-panel figure. ``capture_points``: {'name', 'seconds', 'ssim', 'relative_rmse'}."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    markers = ["o", "s", "^", "D", "v", "P", "X"]
    methods = sorted({p["method"] for p in points})
    hdris = sorted({p["hdri"] for p in points})
    colours = [f"C{i % 10}" for i in range(len(hdris))]
    for ax, key, ylabel in ((fig.add_subplot(1, 2, 1), "ssim", "envmap SSIM (higher is better)"),
                            (fig.add_subplot(1, 2, 2), "relative_rmse", "relative RMSE (lower is better)")):
        for p in points:
            ax.scatter(p["seconds"], p[key], marker=markers[methods.index(p["method"]) % len(markers)],
                       color=colours[hdris.index(p["hdri"])], s=28, alpha=0.8, linewidths=0)
        for c in capture_points:
            if c.get(key) is not None and c.get("seconds"):
                ax.scatter(c["seconds"], c[key], marker="*", color="black", s=140, zorder=3)
                ax.annotate(str(c["name"]), (c["seconds"], c[key]), textcoords="offset points", xytext=(5, 4),
                            fontsize=8)
        ax.set_xscale("log")
        _log_ticks(ax.xaxis)
        if key == "relative_rmse":
            ax.set_yscale("log")
            _log_ticks(ax.yaxis)
        ax.set_xlabel("time: build A + solve (s, 2 cores)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.25)
    # legends: colour = HDRI, marker = method, star = this capture
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], linestyle="", marker="o", color=c, label=h) for h, c in zip(hdris, colours)]
    handles += [Line2D([], [], linestyle="", marker=markers[i % len(markers)], color="grey", label=m)
                for i, m in enumerate(methods)]
    if capture_points:
        handles.append(Line2D([], [], linestyle="", marker="*", color="black", markersize=11, label="this capture"))
    fig.legend(handles=handles, loc="outside right upper", fontsize=8, frameon=False)
    fig.suptitle("Speed against error: benchmark settings (make bench) and this run", fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def load_results(path: Path) -> dict | None:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
