"""The independent numpy/scipy reference of the time-to-accuracy benchmark is itself right:
its forward model reproduces the shared test vector and its explicit adjoints pass a
dot-product and a Taylor test (``scripts/bench/scipy_reference.py --selftest``)."""
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]


def test_reference_selftest():
    proc = subprocess.run([sys.executable, "scripts/bench/scipy_reference.py", "--selftest"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    report = json.loads(proc.stdout)
    assert report["ok"] and report["truth_max_diff"] == 0.0
    assert report["positions_max_diff"] < 1e-11
    assert report["dot_test_rel_dense"] < 1e-10 and report["dot_test_rel_sparse"] < 1e-10
    for kind in ("dense", "sparse"):
        assert min(report[f"taylor_{kind}"]["first_order_rates"]) > 1.9


def test_reference_does_not_import_torch():
    """Independent means no shared code: numpy and scipy only."""
    import ast

    tree = ast.parse((REPO / "scripts" / "bench" / "scipy_reference.py").read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree)
                if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.module}
    assert not imported & {"torch", "torchfit"}, imported
