"""Bench rows say where their times came from (issue 28): a stage found in the cache carries an earlier run's
stage.json, and the tables mark its time; and the core table counts the rows that beat the row-mean oracle."""

from __future__ import annotations

import time

from bench.provenance import seconds_cell, stage_time


def test_a_stage_from_the_cache_is_flagged_and_one_run_now_is_not(tmp_path):
    from objcam.pipeline.cli import main
    from tests.test_bad_input import make_capture

    cap = make_capture(tmp_path / "cap")
    since = time.time()
    assert main(["scene", str(cap), "--quiet"]) == 0
    work = cap / "objcam"
    now = stage_time(work, "scene", since)
    assert not now["cached"] and now["seconds"] > 0
    time.sleep(1.1)  # the record's time is rounded to the second
    later = time.time() + 1.0
    assert main(["scene", str(cap), "--quiet"]) == 0  # unchanged: skipped, its record kept
    again = stage_time(work, "scene", later)
    assert again["cached"] and again["finished"] == now["finished"]
    assert seconds_cell(now["seconds"], True).endswith("(cached)") and "cached" not in seconds_cell(1.0, False)


def test_the_core_table_counts_the_rows_that_beat_the_row_mean_oracle():
    from bench.run import beats_summary

    def row(setting, method, hdri, ssim, tm):
        return {"setting": setting, "method": method, "hdri": hdri,
                "beats_row_mean": {"ssim": ssim, "tonemapped_rmse": tm}}

    rows = [row("auto", "exact (edges)", "forest", True, True), row("auto", "exact (edges)", "sunrise", False, True),
            row("direct K=1", "paper", "forest", False, False), {"setting": "old", "method": "x", "hdri": "city"}]
    lines = beats_summary(rows)
    assert "1 of 3 in SSIM, 2 of 3 in tonemapped RMSE" in lines[1]  # the row without baselines is not counted
    assert "beats it on forest in SSIM and on forest, sunrise in tonemapped RMSE" in lines[2]
    assert beats_summary([{"setting": "auto"}]) == []
