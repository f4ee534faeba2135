"""Where a hard-suite target's SSIM is lost: near its compact sources, or in the sky around them (issue 22).

    python -m bench.hard.decompose [--out /tmp/hard] [--work objcam] [--family lamp]

For every solved target of the family under ``OUT/captures/*/WORK/solve``, the tonemapped SSIM of objcam.metrics
(evaluate's) is scored for the solve's map and for three hybrids with the truth, on the solve's mask:

- ``sources_fixed``: the truth put in the texels within ``GROW`` texels of the truth's sources (texels above
  ``SOURCE_FACTOR`` x the median of the upper hemisphere, azimuth wrapping);
- ``sky_fixed``: the truth everywhere else (the solve's map kept only near the sources);
- ``sky_row_mean``: the solve's sky replaced by its own mean per row (the same energy per elevation, no texture).

A hybrid that scores much higher than the solve's map says where the error is. Prints one line per target and
the medians.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import ndimage

SOURCE_FACTOR = 20.0  # a texel 20 x the sky's median is a source: the suite's lamps and suns are 1e2-1e5 x
GROW = 2  # texels around a source counted as its neighbourhood (the edge prior's halo is 1-3 texels wide)


def source_neighbourhood(truth: np.ndarray, grow: int = GROW, factor: float = SOURCE_FACTOR) -> np.ndarray:
    """(H, 2H) bool: texels within ``grow`` texels (8-neighbours, azimuth wrapping) of the truth's sources.
    truth: (H, 2H, 3) linear radiance."""
    lum = truth.mean(axis=2)
    upper = lum[: lum.shape[0] // 2]
    src = lum > factor * float(np.median(upper[upper > 0])) if (upper > 0).any() else np.zeros(lum.shape, bool)
    if not src.any() or grow <= 0:
        return src
    w = src.shape[1]
    near = ndimage.binary_dilation(np.concatenate([src] * 3, axis=1), np.ones((3, 3), bool), iterations=grow)
    return near[:, :w] | near[:, w:2 * w] | near[:, 2 * w:]


def split_scores(est: np.ndarray, truth: np.ndarray, mask: np.ndarray, grow: int = GROW) -> dict[str, float]:
    """SSIM of ``est`` and of the hybrids of the module docstring. est, truth: (H, 2H, 3) linear radiance on one
    grid; mask: (H, 2H) bool, the texels scored."""
    from objcam.metrics import envmap_metrics

    if est.shape != truth.shape or est.shape[:2] != mask.shape:
        raise ValueError(f"shapes differ: est {est.shape}, truth {truth.shape}, mask {mask.shape}")
    near = source_neighbourhood(truth, grow)
    sky = mask & ~near
    row_mean = est.copy()
    for r in range(est.shape[0]):
        if sky[r].any():
            row_mean[r, sky[r]] = est[r, sky[r]].mean(axis=0)

    def score(e: np.ndarray) -> float:
        return float(envmap_metrics(e, truth, mask)["ssim"])

    return {"ssim": score(est), "sources_fixed": score(np.where(near[..., None], truth, est)),
            "sky_fixed": score(np.where(near[..., None], est, truth)), "sky_row_mean": score(row_mean),
            "source_texels": int(near.sum())}


def main(argv: list[str] | None = None) -> None:
    from objcam.envmap import read_latlong, read_latlong_mask, resample_to_height
    from objcam.stages.evaluate import truth_envmap_path

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/out/hard"), help="bench.hard's --out")
    ap.add_argument("--work", default="objcam", help="the work folder in each capture (objcam-HASH: a --set run)")
    ap.add_argument("--family", default="lamp", help="targets whose name starts with this")
    args = ap.parse_args(argv)
    rows = []
    for cap in sorted((args.out / "captures").glob("*")):
        for sd in sorted((cap / args.work / "solve").glob(f"{args.family}*")):
            if not (sd / "envmap.exr").is_file():
                continue
            est = read_latlong(sd / "envmap.exr")[..., :3].astype(np.float64)
            truth = read_latlong(truth_envmap_path(cap, sd.name))[..., :3].astype(np.float64)
            s = split_scores(est, resample_to_height(truth, est.shape[0]), read_latlong_mask(sd / "envmap_mask.png"))
            rows.append(s)
            print(f"{sd.name:20s} {cap.name[:22]:22s} ssim {s['ssim']:.3f}  sources fixed {s['sources_fixed']:.3f}  "
                  f"sky fixed {s['sky_fixed']:.3f}  sky row mean {s['sky_row_mean']:.3f}")
    if rows:
        keys = ("ssim", "sources_fixed", "sky_fixed", "sky_row_mean")
        print(f"median over {len(rows)}: " + ", ".join(f"{k} {np.median([r[k] for r in rows]):.3f}" for k in keys))


if __name__ == "__main__":
    main()
