"""Two hard-suite runs side by side, per family and paired per target (how session 22 compared prior settings).

    python -m bench.hard.compare BASE_ROWS.json OTHER_ROWS.json [...]

BASE and each OTHER are bench.hard's raw rows (``OUT/rows_full.json``, ``OUT/rows_full-<hash>.json`` of a ``--set``
run, or bench/hard_rows.json). Per family and overall: median and worst SSIM, how many targets beat the row-mean
oracle, the median tonemapped RMSE, the share with the brightest source within one texel (5.6 deg) and with every
band in [0.67, 1.5] (bench.hard.report's counts); then, for each OTHER, the paired SSIM change (min, median, max, and how many targets moved
by more than 0.005 either way) and the medians per noise level.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.hard.report import _band_ok, _solved

MOVED = 0.005  # an SSIM change counted as better or worse


def load_rows(path: Path) -> list[dict]:
    """The solved rows of a bench.hard rows file."""
    return _solved(json.loads(Path(path).read_text())["rows"])


def family_summary(rows: list[dict]) -> dict[str, dict[str, float]]:
    """Per family (and ``all``): n, median and min SSIM, targets beating the row-mean map, median tonemapped
    RMSE, share within one texel and share with every band in [0.67, 1.5]."""
    groups: dict[str, list[dict]] = {"all": rows}
    for r in rows:
        groups.setdefault(r["family"], []).append(r)
    out = {}
    for name, rs in sorted(groups.items()):
        ssim = np.array([r["ssim"] for r in rs])
        rm = np.array([r["baselines"]["row_mean"]["ssim"] for r in rs])
        bands = [_band_ok(r, 0.67, 1.5) for r in rs]  # as the block's own count: a band with no truth fails
        out[name] = {"n": len(rs), "ssim_median": float(np.median(ssim)), "ssim_min": float(ssim.min()),
                     "beats_row_mean": int(np.sum(ssim > rm)),
                     "tonemapped_rmse_median": float(np.median([r["tonemapped_rmse"] for r in rs])),
                     "brightest_within_texel": float(np.mean([r["brightest_angle_deg"] <= 5.6 for r in rs])),
                     "bands_in_range": float(np.mean(bands))}
    return out


def paired(base: list[dict], other: list[dict]) -> dict[str, float]:
    """SSIM of ``other`` minus ``base`` on the targets both solved (matched by target and geometry)."""
    b = {(r["target"], r["geometry"]): r["ssim"] for r in base}
    d = np.array([r["ssim"] - b[(r["target"], r["geometry"])] for r in other if (r["target"], r["geometry"]) in b])
    if d.size == 0:
        return {"n": 0}
    return {"n": int(d.size), "min": float(d.min()), "median": float(np.median(d)), "max": float(d.max()),
            "better": int(np.sum(d > MOVED)), "worse": int(np.sum(d < -MOVED))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base", type=Path)
    ap.add_argument("others", type=Path, nargs="*")
    args = ap.parse_args(argv)
    base = load_rows(args.base)
    for path, rows in [(args.base, base)] + [(p, load_rows(p)) for p in args.others]:
        print(f"== {path}")
        for fam, s in family_summary(rows).items():
            print(f"  {fam:7s} n={s['n']:3d} SSIM median {s['ssim_median']:.3f} min {s['ssim_min']:.3f}, beats "
                  f"row-mean {s['beats_row_mean']:3d}, tm RMSE {s['tonemapped_rmse_median']:.4f}, brightest "
                  f"<= 5.6 deg {s['brightest_within_texel']:.0%}, bands in range {s['bands_in_range']:.0%}")
        for noise in sorted({r["noise"] for r in rows}):
            ss = [r["ssim"] for r in rows if r["noise"] == noise]
            print(f"  noise {noise:g}: median {np.median(ss):.3f}, worst {min(ss):.3f}")
        if rows is not base:
            p = paired(base, rows)
            if p["n"]:
                print(f"  paired against the base ({p['n']} targets): SSIM change min {p['min']:+.3f} median "
                      f"{p['median']:+.3f} max {p['max']:+.3f}; better {p['better']}, worse {p['worse']}")


if __name__ == "__main__":
    main()
