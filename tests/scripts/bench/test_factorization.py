"""Smoke test of scripts/bench/factorization.py: the backends on tiny SPD systems, run as a
user runs it; the JSON layout and each method's backward error. Timings are not asserted.
"""
from __future__ import annotations

import pytest

from helpers.bench_scripts import run_bench_script


@pytest.fixture(scope="module")
def factorization_report(tmp_path_factory) -> dict:
    return run_bench_script("factorization", tmp_path_factory.mktemp("bench") / "factorization.json",
                            "--quick", "--threads", "1")


def test_factorization_layout(factorization_report):
    report = factorization_report
    assert report["benchmark"] == "factorization"
    assert {"torch", "torch_num_threads", "cpu_count"} <= set(report["machine"])
    choice = report["torchfit_choice"]
    assert set(report["matrices"]) == {"chain1d_n1000", "grid2d_N16", "tet3d_2x2x4"}
    for name, mat in report["matrices"].items():
        methods = mat["methods"]
        for label in ("superlu_colamd_default", choice, "superlu_natural",
                      "torchfit_ScipyBackend", "dense_scipy_cho_factor"):
            entry = methods[label]
            assert "error" not in entry, (name, label, entry)
            assert entry["factor"]["median_s"] > 0
            for c in (1, 2):
                assert entry[f"solve_{c}rhs"]["median_s"] > 0
            assert entry["fill_nnz"] >= mat["n"]
            assert entry["backward_error"] < 1e-12, (name, label)
        assert "factor_and_solve_1rhs" in methods["scipy_spsolve"]
        cg = methods["torchfit_CGBackend"]
        assert cg["solve_1rhs"]["converged"] and cg["solve_1rhs"]["iterations"] > 0
        for label in ("cholmod_scikit_sparse", "pypardiso", "torch_sparse_spsolve",
                      "torchfit_PardisoBackend"):
            assert label in methods
            assert "unavailable" in methods[label] or "error" not in methods[label]
        pardiso = methods["torchfit_PardisoBackend"]
        if "unavailable" not in pardiso:
            assert pardiso["analyses"] == 1 and pardiso["backward_error"] < 1e-12
            assert pardiso["analysis_plus_factor"]["median_s"] > 0
        # Symmetric mode never fills more than the default COLAMD LU.
        assert methods[choice]["fill_nnz"] <= methods["superlu_colamd_default"]["fill_nnz"]
        assert methods["torchfit_ScipyBackend"]["fill_nnz"] == methods[choice]["fill_nnz"]
        for key in ("best_by_factor_s", "best_by_factor_plus_1_solve_s",
                    "best_by_factor_plus_10_solves_s"):
            assert mat[key]["fastest"] in methods
    assert "lapack_pttrf_tridiagonal" in report["matrices"]["chain1d_n1000"]["methods"]
