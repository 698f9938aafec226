"""scripts/tools/scale_model.py, the cost model of scripts/bench/scale.py: its pieces are pure
functions, checked against figures worked by hand."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[3] / "scripts" / "tools" / "scale_model.py"
spec = importlib.util.spec_from_file_location("scale_model", SCRIPT)
scale_model = importlib.util.module_from_spec(spec)
spec.loader.exec_module(scale_model)


def test_power_law_recovers_its_exponent():
    sizes = [1e4, 4e4, 1.6e5]
    law = scale_model.fit_power_law(sizes, [2e-6 * n ** 1.3 for n in sizes])
    assert law["b"] == pytest.approx(1.3, rel=1e-12)
    assert law["a"] == pytest.approx(2e-6, rel=1e-9)
    assert not law["b_assumed"]
    assert scale_model.power(law, 3e5) == pytest.approx(2e-6 * 3e5 ** 1.3, rel=1e-9)


def test_power_law_of_one_size_assumes_the_exponent():
    law = scale_model.fit_power_law([1e4], [0.5], default_exponent=1.5)
    assert law["b_assumed"] and law["b"] == 1.5
    assert scale_model.power(law, 4e4) == pytest.approx(0.5 * 4 ** 1.5)
    with pytest.raises(ValueError):
        scale_model.fit_power_law([1e4], [0.0])


def test_communication_bytes_worked_by_hand():
    # 4 frames, 2 ranks, 10 observed vertices, 20 tet vertices, 3 parameters
    gather = scale_model.communication_bytes("gather_J", 4, 2, 10, 20, 3)
    # J: 4 * 10 * 3 * 3 * 8 = 2880 B, positions 4 * 20 * 3 * 8 = 1920 B; rank 0 gets half
    assert gather["rank0_in"] == 2400 and gather["critical"] == 2400
    assert gather["per_rank_out"] == 2 * (10 * 3 * 3 + 20 * 3) * 8
    reduce = scale_model.communication_bytes("allreduce_JtJ", 4, 2, 10, 20, 3)
    # ring all-reduce of 3^2 + 3 doubles: 2 * 1/2 * 12 * 8 = 96 B; half of r: 480 B
    assert reduce["rank0_in"] == 96 + 480
    assert scale_model.communication_bytes("gather_J", 4, 1, 10, 20, 3)["critical"] == 0
    with pytest.raises(ValueError):
        scale_model.communication_bytes("scatter", 4, 2, 10, 20, 3)


def test_prediction_worked_by_hand():
    flat = {"a": 2.0, "b": 0.0}                 # 2 s per frame's trial whatever the size
    column = {"a": 0.5, "b": 0.0}               # 0.5 s per frame and column
    out = scale_model.predict_iteration(
        n_tets=1e5, n_frames=5, n_ranks=2, n_params=3, n_obs=10, n_vertices=20,
        trial_law=flat, column_law=column, flops_per_s=90.0, bandwidth_bytes_per_s=100.0,
        design="gather_J")
    assert out["frames_per_rank"] == 3
    assert out["compute_s"] == pytest.approx(3 * (2.0 + 3 * 0.5))
    assert out["normal_s"] == pytest.approx(5 * 30 * 9 / 90.0)          # rank 0: all rows
    bytes_in = 0.5 * (5 * 30 * 3 * 8 + 5 * 20 * 3 * 8)
    assert out["comm_s"] == pytest.approx(bytes_in / 100.0)
    assert out["seconds"] == pytest.approx(10.5 + 15.0 + bytes_in / 100.0)
    reduce = scale_model.predict_iteration(
        n_tets=1e5, n_frames=5, n_ranks=2, n_params=3, n_obs=10, n_vertices=20,
        trial_law=flat, column_law=column, flops_per_s=90.0, bandwidth_bytes_per_s=100.0,
        design="allreduce_JtJ")
    assert reduce["normal_s"] == pytest.approx(3 * 30 * 9 / 90.0)       # each rank its rows
    one = scale_model.predict_iteration(
        n_tets=1e5, n_frames=5, n_ranks=1, n_params=3, n_obs=10, n_vertices=20,
        trial_law=flat, column_law=column, flops_per_s=90.0, bandwidth_bytes_per_s=1.0)
    assert one["comm_s"] == 0 and one["compute_s"] == pytest.approx(5 * 3.5)
    table = scale_model.prediction_table({"trial": flat, "column": column}, n_tets=1e5,
                                         n_frames=64, ranks=[1, 8, 64],
                                         bandwidths_gbit=[10.0, 1.0], n_params=3, n_obs=10,
                                         n_vertices=20, flops_per_s=1e9)
    assert len(table) == 2 * 2 * 3
    assert [r["frames_per_rank"] for r in table[:3]] == [64, 8, 1]
    assert scale_model.gbit(8.0) == 1e9
