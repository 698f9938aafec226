"""Smoke tests of scripts/bench_gpu.py and scripts/bench_materials.py at tiny sizes (CPU):
the JSON layout, the cost model they report, and that the new small decompositions agree
with LAPACK to round-off. Timings are not asserted."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def run_script(out: Path, name: str, *args: str) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, f"scripts/{name}.py", *args, "--out", str(out)],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report
    return report


def test_bench_gpu_layout_and_counts(tmp_path):
    report = run_script(tmp_path / "gpu.json", "bench_gpu", "--devices", "cpu", "--tet-sizes",
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


def test_bench_materials_agrees_with_lapack(tmp_path):
    report = run_script(tmp_path / "materials.json", "bench_materials", "--n", "3000",
                        "--box", "3", "3", "3", "--repeats", "1")
    kernels = {row["kernel"]: row for row in report["rows"]}
    assert set(kernels) == {"svd2", "neo_hookean_projected_2d", "neo_hookean_projected_3d",
                            "polar_solve", "det3", "tet_box_tangent_projected"}
    for row in kernels.values():
        assert row["max_abs_difference"] < 1e-12, row
        assert row["now_min_s"] > 0 and row["lapack_min_s"] > 0


def test_batched_factorization_row_with_the_nvmath_stand_in():
    """The row that decides whether a Newton round's frames can be factorised as one batch
    (nvmath's explicit batch against one matrix at a time): run with the CPU stand-in, one
    plan each, the same solutions."""
    import importlib.util

    import torch

    from helpers.fake_nvmath import FakeCuda

    sys.path.insert(0, str(REPO / "scripts"))
    spec = importlib.util.spec_from_file_location("bench_gpu", REPO / "scripts/bench_gpu.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    fake = FakeCuda()
    row = bench.batched_factorization_row(3, torch.device("cpu"), 3, runtime=fake)
    assert row["batch"] == 3 and row["free_dofs"] == 3 * 16 * 3
    assert fake.count("plan") == 2 and fake.count("factorize") == 3 + 1
    assert row["max_difference"] < 1e-12
    for key in ("plan_single_s", "factorize_single_each_s", "plan_batch_s", "factorize_batch_s"):
        assert row[key] >= 0

