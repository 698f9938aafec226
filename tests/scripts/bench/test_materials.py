"""Smoke test of scripts/bench/materials.py at tiny sizes: the small 2x2/3x3 decompositions
agree with LAPACK to round-off. Timings are not asserted."""
from __future__ import annotations

from helpers.bench_scripts import run_bench_script


def test_materials_benchmark_agrees_with_lapack(tmp_path):
    report = run_bench_script("materials", tmp_path / "materials.json", "--n", "3000",
                              "--box", "3", "3", "3", "--repeats", "1")
    kernels = {row["kernel"]: row for row in report["rows"]}
    assert set(kernels) == {"svd2", "neo_hookean_projected_2d", "neo_hookean_projected_3d",
                            "polar_solve", "det3", "tet_box_tangent_projected"}
    for row in kernels.values():
        assert row["max_abs_difference"] < 1e-12, row
        assert row["now_min_s"] > 0 and row["lapack_min_s"] > 0
