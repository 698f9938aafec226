"""scripts/bench/scale.py: the script runs as a user runs it on a very coarse arm (about 700
tetrahedra, 2 frames), and its JSON layout and counts are checked, never its timings (the
machine is shared); its model report is checked on cases written by hand. The cost model's
own pieces (scripts/tools/scale_model.py): tests/scripts/tools/test_scale_model.py.
"""
from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
SCRIPT = REPO / "scripts" / "bench" / "scale.py"
# loaded under a name of its own: a module called ``scale`` would be too generic a name
spec = importlib.util.spec_from_file_location("bench_scale", SCRIPT)
bench_scale = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench_scale)


def run_bench(out: Path, *args: str, timeout: float = 300) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "scripts/bench/scale.py", *args, "--out", str(out)],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report, "--out must hold the printed JSON"
    assert "check" in proc.stderr and "predict" in proc.stderr      # the table
    return report


def check_case(case: dict, ranks: int) -> None:
    assert not case.get("failed"), case
    assert case["ranks"] == ranks and case["n_frames"] == 2 and case["n_simulated_frames"] == 2
    assert 300 < case["n_tets"] < 3000 and case["n_params"] == 192
    sim = case["simulate"]
    # frame 9 (bent) needs Newton iterations: a cache hit would show none
    assert sim["counts"]["factorizations"] >= 2 and sim["s"] > 0
    jac = case["jacobian"]
    assert jac["shape"] == [2 * case["n_obs"] * 3, 192]
    assert jac["counts"]["factorizations"] == 0 and jac["counts"]["rhs_columns"] == 2 * 192
    lm = case["lm_accepted"]
    assert lm["iterations"] == 1 and len(lm["misfit"]) == 2
    assert case["peak_rss_MB_rank0"] > 50 and case["peak_rss_MB_any_process"] >= \
        case["peak_rss_MB_rank0"] - 1
    assert len(sim["loadavg"]) == 3


def fake_case(label: str, ranks: int, n_tets: int, per_frame: float, column: float,
              lm_s: float) -> dict:
    """A case as the measuring process writes it (only what the model reads)."""
    frames = 48 if ranks > 1 else 23
    return {"label": label, "ranks": ranks, "n_tets": n_tets, "n_vertices": n_tets // 4,
            "n_frames": 48, "n_simulated_frames": frames, "n_params": 192, "n_obs": 1922,
            "setup": {"cold_build_s": 10.0, "cached_build_s": 1.0},
            "simulate": {"s": per_frame * frames, "per_simulated_frame_s": per_frame,
                         "counts": {"factorizations": 100}, "loadavg": [2.0, 2.0, 2.0],
                         "newton_iterations_rank0": [4] * frames},
            "jacobian": {"s": column * frames * 192, "per_frame_column_s": column,
                         "JtJ_flops_per_s": 1e10},
            "lm_accepted": {"s": lm_s, "accepted": True, "loadavg": [2.0, 2.0, 2.0],
                            "counts": {"factorizations": 2 * frames}},
            "gather_probe": {"bytes_per_s": 1e9} if ranks > 1 else None,
            "peak_rss_MB_rank0": 900.0, "peak_rss_MB_any_process": 950.0}


def test_model_report_fits_and_checks():
    cases = [fake_case("10k", 1, 10_000, 1.0, 1e-3, 30.0),
             fake_case("40k", 1, 40_000, 4.0, 4e-3, 120.0),
             fake_case("10k", 2, 10_000, 1.0, 1e-3, 40.0)]
    namespace = type("Args", (), {"target_tets": 300_000, "target_frames": 500,
                                  "target_ranks": [1, 8, 64], "target_params": 192,
                                  "target_obs": 10_000, "tets_per_vertex": 4.0,
                                  "bandwidths_gbit": [10.0, 1.0]})()
    model = bench_scale.model_report(cases, namespace)
    # per-frame cost 1 s at 10k, 4 s at 40k: exponent 1; the column likewise
    assert model["laws"]["trial"]["b"] == pytest.approx(1.0)
    assert model["laws"]["column"]["b"] == pytest.approx(1.0)
    one, _, two = model["check"]
    # one process, 23 simulated frames: 23 * (1 + 192e-3) s + J^T J 23 * 5766 * 192^2 / 1e10
    normal = 23 * 1922 * 3 * 192 ** 2 / 1e10
    assert one["predicted_s"] == pytest.approx(23 * 1.192 + normal)
    assert one["measured_over_predicted"] == pytest.approx(30.0 / one["predicted_s"])
    # two ranks: 24 frames each, all 48 rows' J^T J on rank 0, half of J over the link
    assert two["n_simulated_frames"] == 48
    assert two["parts"]["compute_s"] == pytest.approx(24 * 1.192)
    gathered = 0.5 * (48 * 5766 * 192 + 48 * 2500 * 3) * 8
    assert two["parts"]["comm_s"] == pytest.approx(gathered / 1e9)
    row = next(r for r in model["prediction"] if r["design"] == "gather_J"
               and r["ranks"] == 64 and r["bandwidth_gbit"] == 1.0)
    assert row["frames_per_rank"] == 8
    assert row["trial_per_frame_s"] == pytest.approx(30.0)        # 1 s x 300k / 10k
    # warm trial: seconds per factorisation (23 / 100 at 10k) x 2 factorisations per frame
    assert model["laws"]["factorization"]["b"] == pytest.approx(1.0)
    assert model["laws"]["trial_warm"]["factorizations_per_frame"] == pytest.approx(2.0)
    assert one["predicted_warm_s"] == pytest.approx(23 * (0.46 + 0.192) + normal)
    assert row["warm_seconds"] < row["seconds"]
    lines = bench_scale.table_lines(cases, model)
    assert len(lines) == 1 + 3 + 3 + 12 and lines[-1].startswith("predict allreduce_JtJ")


def test_a_case_of_the_pose_split_is_checked_with_its_poses_and_the_summed_gram():
    # two ranks share the 23 distinct poses (12 + 11) and sum their J^T J on rank 0
    split = {**fake_case("10k", 2, 10_000, 1.0, 1e-3, 20.0), "n_simulated_frames": 23,
             "split": "poses"}
    cases = [fake_case("10k", 1, 10_000, 1.0, 1e-3, 30.0),
             fake_case("40k", 1, 40_000, 4.0, 4e-3, 120.0), split]
    namespace = type("Args", (), {"target_tets": 300_000, "target_frames": 500,
                                  "target_ranks": [8], "target_params": 192,
                                  "target_obs": 10_000, "tets_per_vertex": 4.0,
                                  "bandwidths_gbit": [10.0]})()
    two = bench_scale.model_report(cases, namespace)["check"][-1]
    assert two["design"] == "allreduce_JtJ" and two["n_simulated_frames"] == 23
    assert two["parts"]["frames_per_rank"] == 12
    assert two["parts"]["compute_s"] == pytest.approx(12 * 1.192)
    assert two["parts"]["normal_s"] == pytest.approx(12 * 1922 * 3 * 192 ** 2 / 1e10)
    # the gram and J^T r all-reduced (half each way), half of the residual gathered
    summed = 2 * 0.5 * (192 ** 2 + 192) * 8 + 0.5 * 23 * 1922 * 3 * 8
    assert two["parts"]["comm_s"] == pytest.approx(summed / 1e9)


@pytest.mark.slow
def test_bench_scale_one_process_json(tmp_path):
    report = run_bench(tmp_path / "scale.json", "--sizes", "tiny:0.12:0.006", "--frames",
                       "tiny=0,9", "--ranks", "1", "--no-rejected", "tiny", "--cache-dir",
                       str(tmp_path / "cache"))
    (case,) = report["cases"]
    check_case(case, 1)
    assert "lm_rejected" not in case
    assert case["setup"]["first_tet_cache_hit"] is False
    assert case["setup"]["cold_build_s"] >= case["setup"]["tetrahedralize_s"]
    model = report["model"]
    assert model["laws"]["trial"]["b_assumed"]          # one size: the exponent assumed
    (check,) = model["check"]
    assert check["measured_over_predicted"] == pytest.approx(
        case["lm_accepted"]["s"] / check["predicted_s"])
    assert len(model["prediction"]) == 2 * 2 * 3        # designs x bandwidths x ranks
    assert {r["ranks"] for r in model["prediction"]} == {1, 8, 64}
    # the model again from the JSON alone
    again = run_bench(tmp_path / "again.json", "--model-only", str(tmp_path / "scale.json"),
                      "--target-ranks", "4")
    assert again["cases"] == report["cases"]
    assert {r["ranks"] for r in again["model"]["prediction"]} == {4}


@pytest.mark.slow
def test_bench_scale_two_ranks_json(tmp_path):
    report = run_bench(tmp_path / "scale.json", "--sizes", "tiny:0.12:0.006", "--frames",
                       "tiny=0,9", "--ranks", "1", "2", "--cache-dir", str(tmp_path / "cache"))
    one, two = report["cases"]
    check_case(one, 1)
    check_case(two, 2)
    assert two["gather_probe"]["bytes_per_s"] > 0
    # the same work on 2 ranks: the Jacobian's columns are counted over every rank
    assert two["jacobian"]["counts"] == one["jacobian"]["counts"]
    assert {"lm_accepted", "lm_rejected"} <= set(two)
    assert math.isfinite(report["model"]["check"][-1]["measured_over_predicted"])


def test_a_killed_runs_figures_are_listed_not_fitted():
    whole = fake_case("10k", 1, 10_000, 1.0, 1e-3, 30.0)
    killed = {key: value for key, value in fake_case("160k", 1, 160_000, 50.0, 5e-2, 0.0)
              .items() if key not in ("jacobian", "lm_accepted", "peak_rss_MB_rank0")}
    killed.update({"partial": True, "returncode": -9})
    namespace = type("Args", (), {"target_tets": 300_000, "target_frames": 500,
                                  "target_ranks": [8], "target_params": 192,
                                  "target_obs": 10_000, "tets_per_vertex": 4.0,
                                  "bandwidths_gbit": [10.0], "fit_labels": []})()
    model = bench_scale.model_report([whole, killed], namespace)
    assert model["fitted_to"] == ["10k"] and model["laws"]["trial"]["b_assumed"]
    assert [row["label"] for row in model["check"]] == ["10k"]
    lines = bench_scale.table_lines([whole, killed], model)
    assert "partial (exit -9): simulate 1150.0 s (50.00 s per simulated frame" in lines[2]
    markdown = bench_scale.markdown_lines({"cases": [whole, killed], "model": model})
    assert markdown[3].startswith("| 160k | 160,000 | 1 | 48 (23) | partial (exit -9)")
