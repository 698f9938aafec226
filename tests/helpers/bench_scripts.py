"""Run a benchmark script of ``scripts/bench/`` as a user runs it, and read its JSON report."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def run_bench_script(name: str, out: Path, *args: str, timeout: float = 120) -> dict:
    """``python scripts/bench/<name>.py ARGS --out OUT`` from the repository root, on one
    thread (stable timings when the 2-core machine is shared); its printed JSON, which
    ``--out`` must hold too."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, f"scripts/bench/{name}.py", *args, "--out", str(out)],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report, "--out must hold the printed JSON"
    return report
