"""Smoke test of scripts/bench/poisson2d.py (tiny grids, run as a user runs it).

Checks the JSON layout and the cost model, which holds at any size: the forward makes
one factorisation (both components share it), backward, ``J v`` and ``J^T w`` reuse it
(one solve each), one Gauss-Newton step with ``m`` CGLS iterations makes one
factorisation per new parameter vector and at most ``2m + 2 + t`` solves. Timings are
not asserted (the machine may be busy).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("bench") / "poisson2d.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "scripts/bench/poisson2d.py", "--sizes", "6", "10",
                           "--gn-sizes", "8", "12", "--repeats", "2", "--threads", "1",
                           "--out", str(out)], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    printed = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == printed, "--out must hold the printed JSON"
    return printed


def test_layout(report):
    assert report["benchmark"] == "poisson2d"
    assert report["machine"]["torch_num_threads"] == 1
    assert set(report["results"]) == {"6", "10"} and set(report["gn_iterations"]) == {"8", "12"}
    for N, res in report["results"].items():
        assert res["n_params"] == (int(N) - 1) ** 2
        for key in ("forward", "backward", "jvp", "vjp"):
            assert res[key]["repeats"] == 2 and 0 < res[key]["min_s"] <= res[key]["median_s"]
        assert res["backward_over_forward"] == pytest.approx(
            res["backward"]["median_s"] / res["forward"]["median_s"])
        assert res["adjoint_check_rel_err"] < 1e-10
        assert res["gn_step"]["cg_iterations_m"] >= 1
    acceptance = report["acceptance"]
    assert acceptance["N"] == 10             # the largest size when 256 is not run
    for key in ("backward_over_forward", "backward_le_0.15x_forward", "gn_iterations",
                "gn_iteration_spread", "gn_iterations_within_30_percent"):
        assert key in acceptance


def test_cost_model_and_discrepancy_stop(report):
    for res in report["results"].values():
        assert all(res["count_checks"].values()), res["count_checks"]
        assert res["forward"]["counts"]["factorizations"] == 1
        assert res["forward"]["counts"]["rhs_columns"] == 2       # both components, one solve
        assert res["backward"]["counts"] == {"factorizations": 0, "solves": 1, "rhs_columns": 2,
                                             "analyses": 0}
    for run in report["gn_iterations"].values():
        assert run["stop_reason"] == "discrepancy"
        assert run["misfit"] <= 1.5 * run["noise_level"]
        assert run["iterations"] == len(run["cg_iterations"])
    assert report["acceptance"]["all_count_checks_pass_at_every_size"]
    assert report["acceptance"]["gn_all_stop_by_discrepancy"]
