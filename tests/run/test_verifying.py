"""torchfit.run.verify: the derivative checks of a problem, verify.json, settings checked first."""
from __future__ import annotations

import json

import pytest

from torchfit.problems import build_problem
from torchfit.run import FitConfigError, verify



def test_verify_writes_its_report_and_checks_its_settings_first(tmp_path):
    problem = build_problem("spring1d", {"n": 16})
    report = verify(problem, run_dir=tmp_path / "ok")
    saved = json.loads((tmp_path / "ok" / "verify.json").read_text())
    assert report.passed and saved["passed"] is True
    assert abs(saved["taylor_rate"] - 2.0) <= 0.05 and saved["dot_product_rel_error"] <= 1e-10
    assert saved["config"]["problem"]["name"] == "spring1d" and saved["point"]["at"] == "initial"
    for bad, message in (({"at": "nowhere"}, "at="), ({"perturbation": -0.5}, "perturbation"),
                         ({"perturbation": float("inf")}, "perturbation"),
                         ({"dot_tol": 0.0}, "dot_tol")):
        with pytest.raises(FitConfigError, match=message):
            verify(problem, run_dir=tmp_path / "bad", **bad)
    assert not (tmp_path / "bad").exists()


def test_verify_on_membrane2d():
    report = verify(build_problem("membrane2d", {"nx": 8, "ny": 4}))
    assert report.passed and abs(report.taylor.rate - 2.0) <= 0.05
