"""scripts/blender/torchfit_blender/results.py: progress and summary from a real run's files."""
from __future__ import annotations

import json

import pytest

from torchfit_blender.results import log_tail, read_progress, read_summary

pytestmark = pytest.mark.slow


def test_progress_and_summary_are_the_runs_history_and_result(finished_run):
    rows = [json.loads(x) for x in (finished_run / "history.jsonl").read_text().splitlines()]
    progress = read_progress(finished_run, max_iter=4)
    assert progress.iteration == rows[-1]["iteration"] == 2
    assert progress.misfit == rows[-1]["misfit"]
    assert progress.surface_error == rows[-1]["surface_err_mean"]
    assert progress.fraction == 0.5
    assert progress.log and not progress.log[-1].startswith("[")
    result = json.loads((finished_run / "result.json").read_text())
    summary = read_summary(finished_run)
    assert summary.surface_error == result["surface_err_mean"]
    assert summary.held_out_error == result["validation_surface_err_mean"] > 0
    assert summary.reduction == result["surface_err_reduction"] > 1
    assert summary.determined is result["determined"]
    assert summary.units == "relative to problem.E0"
    assert summary.iterations == 2 and summary.stop_reason == "max_iter"


def test_a_run_being_written_reads_as_far_as_it_is_whole(tmp_path):
    assert read_progress(tmp_path, 5).iteration == -1 and read_summary(tmp_path) is None
    (tmp_path / "history.jsonl").write_text('{"iteration": 0, "misfit": 2.0}\n'
                                            '{"iteration": 1, "misfit": 1.0, "surface_err_mean": 0.003}\n'
                                            '{"iteration": 2, "mis')
    (tmp_path / "fit.log").write_text("[2026-12-07 21:49:31,544][torchfit.setup][INFO] - a\n"
                                      "[2026-12-07 21:49:32,000][torchfit][WARNING] - b\n")
    progress = read_progress(tmp_path, 4)
    assert (progress.iteration, progress.misfit, progress.surface_error, progress.fraction) == \
        (1, 1.0, 0.003, 0.25)
    assert log_tail(tmp_path) == ["a", "b"]
