"""Bounds on a rigged body's modulus (torchfit.problems.body.bounds): which apply, their
check (one line), their theta, the region report; a capsule fit stays inside them."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.capsule_animation import write_capsule
from helpers.fit_app import run_fit_app
from torchfit import build_problem, fit
from torchfit.problems import ProblemConfigError
from torchfit.problems.body.report import region_summary
from torchfit.problems.config import Transform
from torchfit.problems.body.bounds import (bounds_apply, check_bounds, modulus_bounds,
                                              region_report, theta_bounds)
from torchfit.problems.body.config import RiggedBodyConfig, Target

DATA = Path(__file__).resolve().parents[2] / "data"


def test_defaults_bound_rig_targets_only():
    rig, synthetic = RiggedBodyConfig(E0=2.0), RiggedBodyConfig(E0=2.0, target=Target.synthetic)
    assert bounds_apply(rig) and not bounds_apply(synthetic)
    assert modulus_bounds(rig) == (0.02, 200.0)          # [E0 / 100, 100 E0]
    assert modulus_bounds(synthetic) is None
    assert bounds_apply(RiggedBodyConfig(target=Target.synthetic, bounds=True))
    assert modulus_bounds(RiggedBodyConfig(bounds=False)) is None
    absolute = RiggedBodyConfig(E0=2.0, E_min=0.5, E_max=8.0, E_bounds_relative=False)
    assert modulus_bounds(absolute) == (0.5, 8.0)


def test_theta_bounds_follow_the_transform():
    like = torch.zeros(3, dtype=torch.float64)
    lower, upper = theta_bounds(RiggedBodyConfig(E0=2.0), 3, like)
    assert torch.allclose(lower, torch.full((3,), math.log(0.02), dtype=torch.float64))
    assert torch.allclose(upper, torch.full((3,), math.log(200.0), dtype=torch.float64))
    lower, upper = theta_bounds(RiggedBodyConfig(E0=2.0, transform=Transform.identity), 3, like)
    assert lower.tolist() == [0.02] * 3 and upper.tolist() == [200.0] * 3
    assert theta_bounds(RiggedBodyConfig(bounds=False), 3, like) is None


@pytest.mark.parametrize("settings,words", [
    ({"E_min": 100.0, "E_max": 10.0}, "problem.E_min=100.0: must be below problem.E_max=10.0"),
    ({"E_min": 2.0}, "problem.E0=1.0: lies outside the bounds \\[2, 100\\]"),
    ({"E_min": 0.0}, "problem.E_min=0.0: must be positive"),
    ({"E_min": -1.0}, "problem.E_min=-1.0: must be positive"),
    ({"E0": 5.0, "E_min": 0.1, "E_max": 2.0, "E_bounds_relative": False},
     "problem.E0=5.0: lies outside the bounds \\[0.1, 2\\]"),
])
def test_bad_bounds_are_one_line_naming_the_setting(settings, words):
    with pytest.raises(ProblemConfigError, match=words) as info:
        check_bounds(RiggedBodyConfig(**settings))
    assert "\n" not in str(info.value)
    # without bounds the same settings are not looked at
    check_bounds(RiggedBodyConfig(bounds=False, **settings))


def test_region_summary_counts_the_tetrahedra_on_each_bound():
    values = np.array([0.01, 0.01, 0.5, 100.0, 3.0, 0.01 * (1 + 1e-9)])
    labels = np.array([0, 0, 0, 1, 1, 1])
    out = region_summary(values, np.ones(6), labels, ["a", "b"], bounds=(0.01, 100.0))
    assert out["a"]["at_lower"] == pytest.approx(2 / 3) and out["a"]["at_upper"] == 0.0
    assert out["b"]["at_lower"] == pytest.approx(1 / 3)
    assert out["b"]["at_upper"] == pytest.approx(1 / 3)
    assert "at_lower" not in region_summary(values, np.ones(6), labels, ["a", "b"])["a"]


@pytest.mark.slow
def test_capsule_rig_fit_stays_inside_tight_bounds(tmp_path):
    """Bounds [0.7, 1.4] E0 that bind on the kept capsule mesh: every iterate's field lies
    inside them, some parameters end on a bound, and the fit still lowers the error
    (about 40 s)."""
    shutil.copytree(DATA / "capsule_mesh", tmp_path / "cache")
    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    problem = build_problem("animation", {"path": str(folder), "cache_dir": str(tmp_path / "cache"),
                                          "tet_edge_length": 0.12, "grid": [2, 2, 3],
                                          "newton_rtol": 1e-9, "E_min": 0.7, "E_max": 1.4})
    assert problem.tet.from_cache
    fields = []
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 2, "max_step": 1.0},
                 callbacks=[lambda record: fields.append(problem.field(record.theta))])
    low, high = 0.7 * (1 - 1e-12), 1.4 * (1 + 1e-12)
    assert all(float(f.min()) >= low and float(f.max()) <= high for f in fields)
    assert result.metrics["surface_err_mean"] < problem.report.homogeneous_error()
    last = result.history[-1]
    assert last["at_lower_bound"] + last["at_upper_bound"] >= 1
    summary = problem.report.region_summary(problem.field(result.theta))
    assert all({"at_lower", "at_upper"} <= set(r) for r in summary.values())


@pytest.mark.slow
def test_app_refuses_bad_bounds_in_one_line_and_writes_nothing(tmp_path):
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=animation", f"problem.path={tmp_path}",
                       "problem.E_min=3", "problem.E_max=2", timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "problem.E_min=3" in lines[0], proc.stderr
    assert not run.exists() or not any(run.iterdir())


def test_region_report_counts_the_parameters_on_each_bound_through_the_basis():
    """A grid node on a bound shows in the parameters that act on a region (its pre-image
    under the basis), even where no tetrahedron's blended modulus is on the bound."""
    basis = torch.tensor([[1.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0],
                          [0.0, 0.5, 0.5]], dtype=torch.float64)
    values = torch.tensor([0.01, 1.0, 100.0], dtype=torch.float64)
    labels = np.array([0, 0, 1, 1, 2])
    out = region_report(basis @ values, np.ones(5), labels, ["a", "b", "c"], basis.to_sparse(),
                        (0.01, 100.0))
    assert out["a"]["params"] == 2 and out["a"]["params_at_lower"] == 0.5
    assert out["a"]["params_at_upper"] == 0.0 and out["a"]["at_lower"] == 0.5
    assert out["b"]["params"] == 2 and out["b"]["params_at_upper"] == 0.5
    assert out["c"]["params_at_upper"] == 0.5 and out["c"]["at_upper"] == 0.0
    assert "params" not in region_report(basis @ values, np.ones(5), labels, ["a", "b", "c"],
                                         basis, None)["a"]
