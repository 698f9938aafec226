"""Smoke test of scripts/bench/membrane2d.py (tiny sizes, as a user runs it)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]


def test_membrane2d_benchmark_layout(tmp_path):
    out = tmp_path / "membrane2d.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "scripts/bench/membrane2d.py", "--sizes", "8x2",
                           "16x4", "--repeats", "1", "--models", "linear", "corotated",
                           "--threads", "1", "--out", str(out)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report
    assert report["benchmark"] == "membrane2d" and report["machine"]["torch_num_threads"] == 1
    assert set(report["results"]) == {"linear", "corotated"}
    for model, sizes in report["results"].items():
        assert set(sizes) == {"8x2", "16x4"}
        for res in sizes.values():
            assert len(res["frame"]) == 8
            for key in ("simulate", "backward", "simulate_warm", "jvp", "vjp"):
                assert res[key]["median_s"] > 0
            # backward reuses the forward's factorisations: no new one, one solve per frame
            # (one for all frames with the shared factor of the linear model)
            assert res["backward"]["counts"]["factorizations"] == 0
            assert res["backward"]["counts"]["solves"] == (1 if model == "linear" else 8)
            iterations = res["simulate"]["newton_iterations"]
            assert len(iterations) == 8
            if model == "linear":
                assert iterations == [1] * 8 and res["simulate"]["counts"]["factorizations"] == 1
            else:
                assert all(1 <= i <= 10 for i in iterations)
                assert res["simulate_warm"]["warm_started"] is True
