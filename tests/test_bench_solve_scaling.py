"""bench/solve_scaling.py's summary: per-round medians, the ratio of the medians, and issue 26's target line."""

from __future__ import annotations

from bench.solve_scaling import summarize, table


def _raw(s32: list[float], s64: list[float], kkt64: float = 8e-13) -> dict:
    run = lambda s, k: {"seconds": s, "cpu": 1.6 * s, "kkt": k}  # noqa: E731
    return {"heights": [32, 64], "load": (0.5, 0.7),
            "rounds": [{"probe_ms": 4.2, "runs": {"32": [run(a, 1e-15) for a in s32[i:i + 3]],
                                                  "64": [run(b, kkt64) for b in s64[i:i + 3]]}}
                       for i in (0, 3)]}


def test_the_ratio_of_medians_decides_the_target():
    raw = _raw([0.14, 0.12, 0.13, 0.15, 0.14, 0.16], [1.2, 1.4, 1.3, 1.5, 1.45, 1.6])
    rows, overall = summarize(raw)
    assert [round(r["ratio"], 2) for r in rows] == [10.0, 1.5 / 0.15]  # (median 1.3 / 0.13, 1.5 / 0.15)
    text = table(raw, rows, overall)
    assert "- met: 64 x 128 <= 10x the 32 x 64 solve" in text and "median ratio 10.0x" in text  # (exactly 10x)
    assert "(rounds 10.0-10.0x)" in text and "KKT <= 8.0e-13" in text
    # broken: a slower 64 x 128 solve, or one not exact to 1e-8, misses
    slow = _raw([0.14, 0.12, 0.13, 0.15, 0.14, 0.16], [1.5, 1.6, 1.55, 1.7, 1.65, 1.8])
    assert "**missed**" in table(slow, *summarize(slow))
    loose = _raw([0.14, 0.12, 0.13, 0.15, 0.14, 0.16], [1.2, 1.4, 1.3, 1.5, 1.45, 1.6], kkt64=3e-8)
    assert "**missed**" in table(loose, *summarize(loose))
