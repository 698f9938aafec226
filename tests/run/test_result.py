"""What a run returns and what its result.json holds."""
from __future__ import annotations

import math

import torch

from torchfit.problems import build_problem
from torchfit.run import FitResult
from torchfit.run.identifiability import from_jacobian
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
    assert "\n" not in line and line.startswith("misfit 5.000e-01")
    assert line.endswith("stopped by discrepancy after 3 iterations (converged) in 1.2 s, "
                         "4 factorizations, 9 solves")


def test_a_bodys_summary_says_what_a_td_reads():
    """The surface error (mean, max, reduction) on the fitted and held-out frames, the
    verdict on the data, the stop reason: one line, in millimetres."""
    body = {"misfit": 0.507, "surface_err_mean": 5.49e-4, "surface_err_max": 0.0112,
            "surface_err_reduction": 12.4}
    validation = {"iteration": 4, "params": "params_best_validation.pt",
                  "final": {"surface_err_mean": 6.1e-4, "surface_err_max": 0.0098,
                            "surface_err_reduction": 2.21},
                  "chosen": {"surface_err_mean": 6.0e-4, "surface_err_reduction": 2.3}}
    line = result(metrics=body, stop_reason="max_iter", converged=False,
                  validation=validation).summary()
    assert "\n" not in line
    assert line.startswith("surface error on the fitted frames 0.549 mm mean, 11.2 mm max, "
                           "12.4x below the homogeneous material; on the held-out frames "
                           "0.61 mm mean, 9.8 mm max, 2.21x below the homogeneous material "
                           "(best held-out at iteration 4: 0.6 mm mean, "
                           "params_best_validation.pt)")
    assert "stopped by max_iter after 3 iterations (not converged)" in line
    assert line.endswith("misfit 5.070e-01")
    report = from_jacobian(torch.zeros(4, 2), torch.zeros(2), torch.ones(4), "exp",
                           source="test")
    undetermined = result(metrics=body, converged=False, identifiability=report).summary()
    assert "; the data do NOT determine the material: the outputs keep the starting field" \
        in undetermined and "(not converged)" in undetermined


def test_held_out_frames_worse_than_homogeneous_say_so():
    body = {"misfit": 0.507, "surface_err_mean": 5.49e-4, "surface_err_max": 0.0112,
            "surface_err_reduction": 1.01}
    validation = {"iteration": 0, "params": "params_best_validation.pt",
                  "final": {"surface_err_mean": 6.3e-4, "surface_err_reduction": 0.97},
                  "chosen": {"surface_err_mean": 6.1e-4, "surface_err_reduction": 1.0}}
    line = result(metrics=body, validation=validation).summary()
    assert ("on the held-out frames 0.63 mm mean, 0.97x below the homogeneous material "
            "(best held-out at iteration 0: 0.61 mm mean, params_best_validation.pt); the "
            "held-out frames are WORSE than with the homogeneous material (0.97x): the fitted "
            "material does not carry over to them; stopped by") in line
    validation["final"]["surface_err_reduction"] = 1.0      # as good, not worse: no warning
    assert "WORSE" not in result(metrics=body, validation=validation).summary()


def test_result_json_keys_in_their_order():
    problem = build_problem("spring1d", {"n": 2})
    out = result_dict(problem, result(resumed_from=2), {"problem": {"n": 2}})
    assert list(out) == ["misfit", "k_err_rel", "iterations", "wall_s", "factorizations",
                         "solves", "converged", "stop_reason", "status",
                         "resumed_from_iteration", "problem", "config", "history"]
    assert out["status"] == "completed" and out["resumed_from_iteration"] == 2
    assert "resumed_from_iteration" not in result_dict(problem, result(), {})


def test_an_undetermined_fit_says_so_beside_its_stop_reason():
    flat = torch.zeros(4, 2, dtype=torch.float64)
    report = from_jacobian(flat, torch.zeros(2, dtype=torch.float64),
                           torch.arange(4.0, dtype=torch.float64))
    done = result(identifiability=report)
    assert done.determined is False and result().determined is None
    assert "the data do NOT determine the material" in done.summary()
    assert "after 3 iterations (not converged) in 1.2 s" in done.summary()
    out = result_dict(build_problem("spring1d", {"n": 2}), done, {})
    assert out["converged"] is True and out["stop_reason"] == "discrepancy"
    assert out["determined"] is False
    assert out["identifiability"] == {"determined": False, "n_params": 2, "n_determined": 0,
                                      "effective_rank": 0, "source": "", "effect": 0.0,
                                      "reduction": None, "reason": report.reason,
                                      "cause": "effect"}
    assert list(out).index("determined") == list(out).index("status") + 1
