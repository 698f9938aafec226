"""TensorBoard tags of a run's values and the HParams values of its settings."""
from __future__ import annotations

from torchfit.reporting.tags import hparam_values, metric_tag, tag_for


def test_tag_scheme():
    assert tag_for("misfit") == "fit/misfit"
    assert tag_for("objective") == "fit/objective"
    for key in ("u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel", "k_err_rel_aligned"):
        assert tag_for(key) == f"metrics/{key}"
    for key in ("cg_iterations", "damping", "step_norm", "solves", "factorizations",
                "wall_time", "eta", "gain_ratio"):
        assert tag_for(key) == f"solver/{key}"
    assert tag_for("custom/thing") == "custom/thing"


def test_metric_tags_and_hparam_values():
    assert metric_tag("misfit") == "fit/misfit"
    assert metric_tag("k_err_rel_aligned") == "metrics/k_err_rel_aligned"
    assert metric_tag("iterations") == "final/iterations"
    assert metric_tag("wall_s") == "final/wall_s"
    assert hparam_values({"solver": {"mu": None, "isotropic": True, "weights": [1, 2]},
                          "problem": {"N": 32}}) == {
        "solver.isotropic": True, "solver.weights": "[1, 2]", "problem.N": 32}
