"""Smoke test of scripts/bench/spring1d.py: tiny sizes, run as a user runs it (subprocess).

It checks the JSON layout and the cost model the benchmarks report, which holds at any
size: backward and ``J v`` reuse the forward's factorisation (0 new ones, 1 solve each);
one Gauss-Newton step with ``m`` CGLS iterations makes one factorisation per new
parameter vector it evaluates and at most ``2m + 1 + t`` solves (``t`` trial points of
the line search), i.e. ``2m + 2`` when the full step is accepted. Timings are not
asserted (the machine may be busy).
"""
from __future__ import annotations

import pytest

from helpers.bench_scripts import run_bench_script


@pytest.fixture(scope="module")
def spring1d_report(tmp_path_factory) -> dict:
    return run_bench_script("spring1d", tmp_path_factory.mktemp("bench") / "spring1d.json",
                            "--sizes", "100", "1000", "--repeats", "2", "--gn-repeats", "1",
                            "--threads", "1")


def test_spring1d_layout(spring1d_report):
    report = spring1d_report
    assert report["benchmark"] == "spring1d"
    machine = report["machine"]
    for key in ("torch", "torch_num_threads", "cpu_count", "scipy", "numpy"):
        assert key in machine
    assert machine["torch_num_threads"] == 1
    assert set(report["results"]) == {"100", "1000"}
    for res in report["results"].values():
        for key in ("forward", "backward", "jvp", "vjp"):
            assert res[key]["median_s"] > 0 and res[key]["min_s"] <= res[key]["median_s"]
            assert res[key]["repeats"] == 2
            assert set(res[key]["counts"]) >= {"factorizations", "solves"}
        for key in ("backward_over_forward", "gn_cg_iterations_m", "gn_factorizations",
                    "gn_solves", "gn_solves_bound", "gn_step", "gn_step_cold",
                    "gn_step_near_truth", "count_checks", "strict_checks"):
            assert key in res
        assert res["backward_over_forward"] == pytest.approx(
            res["backward"]["median_s"] / res["forward"]["median_s"])
        assert res["adjoint_check_rel_err"] < 1e-8
    largest = report["results"]["1000"]
    assert "forward_breakdown" in largest and "profile" in largest
    assert {"forward", "backward", "jvp"} <= set(largest["profile"])
    acceptance = report["acceptance"]
    assert acceptance["n"] == 1000  # the largest size when 1e5 is not run
    for key in ("backward_over_forward", "backward_le_0.3x_forward", "gn_solves",
                "gn_solves_bound", "gn_solves_le_2m_plus_2",
                "gn_one_factorization_per_distinct_theta"):
        assert key in acceptance


def test_spring1d_backward_and_jvp_reuse_the_factorisation(spring1d_report):
    for res in spring1d_report["results"].values():
        assert res["forward"]["counts"]["factorizations"] == 1
        assert res["forward"]["counts"]["solves"] == 1
        for key in ("backward", "jvp", "vjp"):
            assert res[key]["counts"]["factorizations"] == 0, key
            assert res[key]["counts"]["solves"] == 1, key
            assert "inconsistent_across_repeats" not in res[key]["counts"]


def test_spring1d_gn_step_cost(spring1d_report):
    for res in spring1d_report["results"].values():
        for key in ("gn_step", "gn_step_cold", "gn_step_near_truth"):
            gn = res[key]
            m, t = gn["cg_iterations_m"], gn["line_search_trials_t"]
            counts = gn["counts"]
            assert m >= 1
            # One factorisation per distinct parameter vector not evaluated before.
            assert counts["factorizations"] == gn["new_theta_evaluated"], key
            assert gn["new_theta_evaluated"] == t + (0 if gn["warm_start"] else 1)
            cold = 0 if gn["warm_start"] else 1
            assert gn["gn_solves_bound"] == 2 * m + 2 + cold
            assert counts["solves"] <= 2 * m + 1 + t + cold, key
            if gn["accepted_full_step"]:
                assert counts["factorizations"] == 1 + cold
                assert counts["solves"] <= gn["gn_solves_bound"]
            # The solver's own record agrees with the counters.
            assert gn["solver_counts"]["factorizations"] == counts["factorizations"]
            assert gn["solver_counts"]["solves"] == counts["solves"]
        # Near the truth the full step is accepted: exactly 1 factorisation, <= 2m + 2 solves.
        near = res["gn_step_near_truth"]
        assert near["accepted_full_step"]
        assert near["counts"]["factorizations"] == 1
        assert near["counts"]["solves"] <= 2 * near["cg_iterations_m"] + 2
        assert all(res["count_checks"].values()), res["count_checks"]
    assert spring1d_report["acceptance"]["all_count_checks_pass_at_every_size"]
