"""Run-directory files: strict JSON, atomic and byte-identical saves."""
from __future__ import annotations

import json
import os

import numpy as np
import torch

from torchfit.reporting.results import save_params, save_torch, write_json

def test_write_json_is_strict_and_atomic(tmp_path):
    path = write_json(tmp_path / "result.json", {"misfit": 0.5, "odd": float("nan"),
                                                "big": float("inf"), "rows": [{"x": float("-inf")}],
                                                "theta": torch.tensor([1.0, 2.0])})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"misfit": 0.5, "odd": None, "big": None, "rows": [{"x": None}],
                                "theta": [1.0, 2.0]}
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]   # no temporary left


def test_save_params(tmp_path):
    theta = torch.linspace(0, 1, 5)
    params_path, field_path = save_params(tmp_path, theta, theta.exp(), "k")
    saved = torch.load(params_path, weights_only=True)
    assert torch.equal(saved["theta"], theta) and torch.equal(saved["field"], theta.exp())
    assert np.array_equal(np.load(field_path), theta.exp().numpy())


SAVE_OUTPUTS = """
import sys
import torch
from torchfit.reporting.results import save_params, save_torch
run_dir = sys.argv[1]
theta = torch.linspace(-1.0, 2.0, 7, dtype=torch.float64)
save_params(run_dir, theta, torch.exp(theta), "k")
save_torch(run_dir + "/checkpoint.pt", {"iteration": 3, "theta": theta, "problem": "spring1d"})
"""


def test_outputs_are_byte_identical_across_directories_and_processes(tmp_path):
    """The same content gives the same bytes of params.pt, checkpoint.pt and field.npy,
    whatever the directory's name and the process (the temporary file's name used to end
    up inside torch's zip archive)."""
    import subprocess
    import sys

    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {**os.environ, "PYTHONPATH": repo + os.pathsep + os.environ.get("PYTHONPATH", "")}
    dirs = [tmp_path / "first", tmp_path / "second_run_with_a_longer_name"]
    for d in dirs:
        proc = subprocess.run([sys.executable, "-c", SAVE_OUTPUTS, str(d)], env=env,
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
    # and once more in this process
    theta = torch.linspace(-1.0, 2.0, 7, dtype=torch.float64)
    dirs.append(tmp_path / "in_process")
    save_params(dirs[-1], theta, torch.exp(theta), "k")
    save_torch(dirs[-1] / "checkpoint.pt", {"iteration": 3, "theta": theta, "problem": "spring1d"})
    for name in ("params.pt", "checkpoint.pt", "field.npy"):
        contents = [(d / name).read_bytes() for d in dirs]
        assert contents[0] == contents[1] == contents[2], name
        assert b".tmp" not in contents[0], name
    assert sorted(p.name for p in dirs[0].iterdir()) == ["checkpoint.pt", "field.npy",
                                                         "params.pt"]   # no temporary left
    with open(dirs[0] / "checkpoint.pt", "rb") as f:
        loaded = torch.load(f, weights_only=True)
    assert loaded["iteration"] == 3 and torch.equal(loaded["theta"], theta)
