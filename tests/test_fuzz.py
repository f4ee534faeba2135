"""Issue 24: generated captures (valid, near-valid, hostile; bench/fuzz_captures.py) through the real CLI. Every
run must end with finite artifacts (exit 0) or exit 2 and one line naming the file: never a traceback, never a
hang (a 60 s alarm per run), never a write outside the work folder. The long run is `make bench BENCH=fuzz`."""

from __future__ import annotations

import tempfile
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from bench.fuzz_captures import draw_capture, run_case

SUITE_EXAMPLES = 250
SEEN: Counter = Counter()


@settings(max_examples=SUITE_EXAMPLES, deadline=None, database=None, derandomize=True,
          phases=[Phase.generate], suppress_health_check=list(HealthCheck))
@given(st.data())
def test_generated_captures_end_well_at_the_scene_stage(data):
    with tempfile.TemporaryDirectory(prefix="objcam-fuzz-") as tmp:
        sandbox = Path(tmp)
        recipe = draw_capture(data.draw, sandbox)
        out = run_case(sandbox, ["scene"])
        SEEN[out.kind] += 1
        assert out.kind in ("ok", "refused"), (recipe, out)


def test_the_generator_makes_both_kinds():
    """The property above must not pass vacuously: the generated captures include runs that pass and runs that
    are refused (run after it, in file order)."""
    if not SEEN:
        pytest.skip("run with the property test")
    assert SEEN["ok"] >= 0.1 * SUITE_EXAMPLES and SEEN["refused"] >= 0.3 * SUITE_EXAMPLES, SEEN


@settings(max_examples=8, deadline=None, database=None, derandomize=True, phases=[Phase.generate],
          suppress_health_check=list(HealthCheck))
@given(st.data())
def test_generated_captures_end_well_through_the_solve(data):
    with tempfile.TemporaryDirectory(prefix="objcam-fuzz-") as tmp:
        sandbox = Path(tmp)
        recipe = draw_capture(data.draw, sandbox)
        out = run_case(sandbox, ["run", "--until", "solve", "--set", "transport.env_height=8",
                                 "--set", "transport.model=direct"])
        assert out.kind in ("ok", "refused"), (recipe, out)
