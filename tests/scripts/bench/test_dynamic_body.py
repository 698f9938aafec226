"""scripts/bench/dynamic_body.py: its arguments (the figures themselves: docs/notes/dynamics.md)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]


def test_a_long_simulate_needs_a_fitted_run():
    done = subprocess.run([sys.executable, "scripts/bench/dynamic_body.py", "--no-iteration",
                           "--simulate-frames", "240"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2
    assert "--simulate-frames needs --run" in done.stderr.splitlines()[-1]
