"""The fit app (``experiments/fit.py``) as the app tests run it: in the test's process
(:func:`run_fit_app`, through :func:`helpers.apps.run_app`) or, where the test is about a
process (a kill, SIGTERM, two runs at once, a full disk), as a subprocess
(:func:`fit_app_command`, :func:`run_fit_app_process`)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Sequence

from helpers.apps import REPO, run_app

__all__ = ["REPO", "with_problem", "run_fit_app", "run_fit_app_process", "fit_app_command",
           "app_environment"]


def with_problem(overrides: Sequence[str], default: str = "spring1d") -> list[str]:
    """``overrides`` plus ``problem=<default>`` unless they choose a problem or a preset.

    The app's own default (no argument) is the short arm (``problem=arm3d_short``); most
    tests exercise the app on the quick spring1d chain instead, named explicitly.
    """
    chosen = any(o.startswith(("problem=", "experiment=", "+experiment=")) for o in overrides)
    return list(overrides) if chosen else [*overrides, f"problem={default}"]


def run_fit_app(run_dir: Path, *overrides: str, timeout: float = 300,
                env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``python experiments/fit.py hydra.run.dir=<run_dir> <overrides>`` from the repository
    root, in this process (spring1d unless ``overrides`` choose a problem,
    :func:`with_problem`): its exit status, standard output and standard error."""
    return run_app("fit.py", f"hydra.run.dir={run_dir}", *with_problem(overrides), env=env,
                   timeout=timeout)


def app_environment() -> dict[str, str]:
    """The environment of an app subprocess: this one without ``HYDRA_FULL_ERROR``."""
    return {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}


def fit_app_command(run_dir: Path, *overrides: str) -> list[str]:
    """The command line of :func:`run_fit_app_process` (no problem added)."""
    return [sys.executable, "experiments/fit.py", f"hydra.run.dir={run_dir}", *overrides]


def run_fit_app_process(run_dir: Path, *overrides: str,
                        timeout: float = 300) -> subprocess.CompletedProcess:
    """:func:`run_fit_app` in a subprocess of its own: for a test whose point is the
    process (and the one subprocess smoke test of the app)."""
    return subprocess.run(fit_app_command(run_dir, *with_problem(overrides)), cwd=REPO,
                          env=app_environment(), capture_output=True, text=True,
                          timeout=timeout)
