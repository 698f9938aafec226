"""The fit app (``experiments/fit.py``) as a subprocess, as the app tests run it."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Sequence

REPO = Path(__file__).resolve().parents[2]


def with_problem(overrides: Sequence[str], default: str = "spring1d") -> list[str]:
    """``overrides`` plus ``problem=<default>`` unless they choose a problem or a preset.

    The app's own default (no argument) is the short arm (``problem=arm3d_short``); most
    tests exercise the app on the quick spring1d chain instead, named explicitly.
    """
    chosen = any(o.startswith(("problem=", "experiment=", "+experiment=")) for o in overrides)
    return list(overrides) if chosen else [*overrides, f"problem={default}"]


def run_fit_app(run_dir: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``experiments/fit.py`` in a subprocess with its run directory at ``run_dir``
    (spring1d unless ``overrides`` choose a problem, :func:`with_problem`)."""
    overrides = tuple(with_problem(overrides))
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "experiments/fit.py", f"hydra.run.dir={run_dir}",
                           *overrides], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout)
