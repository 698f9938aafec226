"""Smoke test of scripts/bench/gpu.py at tiny sizes on the CPU: the JSON layout and the
cost model it reports. Timings are not asserted."""
from __future__ import annotations

from helpers.bench_scripts import run_bench_script


def test_gpu_benchmark_layout_and_counts(tmp_path):
    report = run_bench_script("gpu", tmp_path / "gpu.json", "--devices", "cpu", "--tet-sizes", "3",
                               "--poisson-sizes", "8", "--threads", "1",
                        "--compare-host-pattern")
    assert report["benchmark"] == "gpu"
    tet, poisson = report["rows"]
    assert (tet["problem"], tet["tets"], tet["device"]) == ("tetbox", 6 * 27, "cpu")
    assert tet["free_dofs"] == 3 * 16 * 2          # 4 x 4 x 4 vertices, bottom and top fixed
    for key in ("mesh_s", "model_s", "equilibrium_s", "total_s", "pattern_host_numpy_s"):
        assert tet["setup"][key] >= 0
    # linear: one factorisation and one solve forward; backward reuses it (one solve)
    assert tet["forward"]["counts"]["factorizations"] == 1
    assert tet["backward"]["counts"] == {"factorizations": 0, "solves": 1, "rhs_columns": 1}
    assert tet["memory"]["peak_rss_mb"] > 0
    assert poisson["problem"] == "poisson2d" and poisson["backward"]["counts"]["factorizations"] == 0
    m = poisson["gn_step"]["cg_iterations"]
    assert poisson["gn_step"]["counts"]["solves"] <= 2 * m + 4
