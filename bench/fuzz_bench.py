"""`make bench BENCH=fuzz`: the long fuzz run of issue 24. Generates captures (bench/fuzz_captures.py: valid,
near-valid, hostile), runs each through the real CLI in this process and counts how every run ended; writes the
counts into bench/results.md (``--write``). Targets: 0 tracebacks, 0 hangs, 0 writes outside the work folder, 0
multi-line or internal ("please report it") messages, 0 non-finite artifacts over >= 2,000 captures.

    python -m bench.fuzz_bench [--n 2000] [--solve-every 10] [--seed 0] [--write]

Every capture runs the scene stage; every ``--solve-every``-th one runs on through the solve (8 x 16 envmap,
direct light) so the later stages see what the scene stage lets through.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections import Counter
from pathlib import Path

from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import seed as hyp_seed
from hypothesis import strategies as st

from bench.fuzz_captures import draw_capture, run_case

SOLVE_ARGS = ["run", "--until", "solve", "--set", "transport.env_height=8", "--set", "transport.model=direct"]
FAILURES = ("traceback", "hang", "write_outside", "bad_message", "non_finite")


def fuzz(n: int, solve_every: int, seed: int, log=print) -> dict:
    """Run ``n`` generated captures; return the counts, the examples of each failure and the time taken."""
    counts: Counter = Counter()
    by_stage: Counter = Counter()
    examples: dict[str, list] = {}
    index = [0]
    t0 = time.perf_counter()

    @settings(max_examples=n, deadline=None, database=None, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(st.data())
    def one(data):
        i = index[0]
        index[0] += 1
        argv = SOLVE_ARGS if solve_every and i % solve_every == 0 else ["scene"]
        with tempfile.TemporaryDirectory(prefix="objcam-fuzz-") as tmp:
            recipe = draw_capture(data.draw, Path(tmp))
            out = run_case(Path(tmp), argv)
        counts[out.kind] += 1
        by_stage[(argv[0], out.kind)] += 1
        if out.kind in FAILURES:
            examples.setdefault(out.kind, []).append((recipe, out.message))
            log(f"[{i}] {out.kind}: {recipe} {out.message[-300:]}")
        if i % 100 == 0:
            log(f"{i} captures, {dict(counts)}, {time.perf_counter() - t0:.0f} s")

    hyp_seed(seed)(one)()
    return {"counts": counts, "by_stage": by_stage, "examples": examples, "n": sum(counts.values()),
            "seconds": time.perf_counter() - t0}


def table(res: dict, argv: list[str] | None) -> str:
    from bench.sections import invocation

    c = res["counts"]
    rows = [f"{invocation('bench.fuzz_bench', argv)}: {res['n']:,} generated captures in "
            f"{res['seconds'] / 60:.1f} min (2 cores, in one process).", "",
            "| ended as | scene only | through the solve | total |", "|---|---:|---:|---:|"]
    for kind in ("ok", "refused") + FAILURES:
        s, r = res["by_stage"][("scene", kind)], res["by_stage"][("run", kind)]
        rows.append(f"| {kind} | {s:,} | {r:,} | {c[kind]:,} |")
    rows += ["", "`ok`: exit 0 with every EXR/NPZ artifact finite; `refused`: exit 2 and one line naming the file "
             "and the fix; the rest are failures (target: 0 each)."]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--solve-every", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write", action="store_true", help="write the counts into bench/results.md")
    args = ap.parse_args(argv)
    res = fuzz(args.n, args.solve_every, args.seed)
    body = table(res, argv)
    print(body)
    if args.write:
        from bench.sections import write_section

        write_section("fuzz", body, "Hostile inputs: the fuzz run (issue 24)")
    return 1 if any(res["counts"][k] for k in FAILURES) else 0


if __name__ == "__main__":
    raise SystemExit(main())
