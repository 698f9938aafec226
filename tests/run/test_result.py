"""What a run returns and what its result.json holds."""
from __future__ import annotations

import math

import torch

from torchfit.problems import build_problem
from torchfit.run import FitResult
from torchfit.run.result import result_dict


def result(**changes) -> FitResult:
    values = dict(theta=torch.zeros(2), field=torch.ones(2),
                  metrics={"misfit": 0.5, "k_err_rel": math.nan}, iterations=3, wall_s=1.25,
                  factorizations=4, solves=9, converged=True, stop_reason="discrepancy",
                  history=[{"iteration": 0, "misfit": 1.0}])
    values.update(changes)
    return FitResult(**values)


def test_value_ranks_what_is_not_finite_last_and_summary_is_one_line():
    done = result()
    assert done.value("misfit") == 0.5 and done.value("iterations") == 3.0
    assert done.value("k_err_rel") == math.inf
    line = done.summary()
    assert "\n" not in line and line.startswith("discrepancy after 3 iterations (converged)")
    assert "misfit 5.000e-01" in line


def test_result_json_keys_in_their_order():
    problem = build_problem("spring1d", {"n": 2})
    out = result_dict(problem, result(resumed_from=2), {"problem": {"n": 2}})
    assert list(out) == ["misfit", "k_err_rel", "iterations", "wall_s", "factorizations",
                         "solves", "converged", "stop_reason", "status",
                         "resumed_from_iteration", "problem", "config", "history"]
    assert out["status"] == "completed" and out["resumed_from_iteration"] == 2
    assert "resumed_from_iteration" not in result_dict(problem, result(), {})
