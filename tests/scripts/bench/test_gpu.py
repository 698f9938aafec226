"""Smoke test of scripts/bench/gpu.py at tiny sizes on the CPU: the JSON layout and the
cost model it reports (analyses, factorisations, solves), and the row of nvmath's batched
factorisation with the stand-in for nvmath. Timings are not asserted."""
from __future__ import annotations

import importlib.util
import sys

import torch

from helpers.bench_scripts import REPO, run_bench_script


def test_gpu_benchmark_layout_and_counts(tmp_path):
    report = run_bench_script("gpu", tmp_path / "gpu.json", "--devices", "cpu", "--tet-sizes",
                              "3", "--poisson-sizes", "8", "--threads", "1",
                              "--compare-host-pattern")
    assert report["benchmark"] == "gpu"
    init, tet, poisson = report["rows"]
    assert init["problem"] == "device_init" and init["autograd_warm_up_s"] >= 0
    assert (tet["problem"], tet["tets"], tet["device"]) == ("tetbox", 6 * 27, "cpu")
    assert tet["free_dofs"] == 3 * 16 * 2          # 4 x 4 x 4 vertices, bottom and top fixed
    for key in ("mesh_s", "model_s", "equilibrium_s", "total_s", "pattern_host_numpy_s",
                "rest_shape_s", "pattern_s"):
        assert tet["setup"][key] >= 0
    # linear: one factorisation and one solve forward; backward reuses it (one solve), again
    assert tet["forward"]["counts"]["factorizations"] == 1
    for key in ("backward", "backward_again"):
        assert tet[key]["counts"] == {"factorizations": 0, "solves": 1, "rhs_columns": 1,
                                      "analyses": 0}
    # the next point: a new factorisation, the pattern's analysis kept
    assert tet["forward_again"]["counts"]["factorizations"] == 1
    assert tet["forward_again"]["counts"]["analyses"] == 0
    assert tet["memory"]["peak_rss_mb"] > 0
    assert poisson["problem"] == "poisson2d" and poisson["backward"]["counts"]["factorizations"] == 0
    m = poisson["gn_step"]["cg_iterations"]
    assert poisson["gn_step"]["counts"]["solves"] <= 2 * m + 4


def test_batched_factorization_row_with_the_nvmath_stand_in():
    """The row that decides whether a Newton round's frames can be factorised as one batch
    (nvmath's explicit batch against one matrix at a time): run with the CPU stand-in, one
    plan each, the same solutions."""
    from helpers.fake_nvmath import FakeCuda

    sys.path.insert(0, str(REPO / "scripts" / "bench"))
    spec = importlib.util.spec_from_file_location("bench_gpu", REPO / "scripts/bench/gpu.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    fake = FakeCuda()
    row = bench.batched_factorization_row(3, torch.device("cpu"), 3, runtime=fake)
    assert row["batch"] == 3 and row["free_dofs"] == 3 * 16 * 3
    assert fake.count("plan") == 2 and fake.count("factorize") == 3 + 1
    assert row["max_difference"] < 1e-12
    for key in ("plan_single_s", "factorize_single_each_s", "plan_batch_s", "factorize_batch_s"):
        assert row[key] >= 0
