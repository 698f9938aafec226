"""Shared pytest fixtures and helpers: paths to the repo and the independent test vectors,
the fit app as a subprocess, a residual that records its linearisation points."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import torchfit  # noqa: F401  (sets float64 as the default dtype)
from torchfit.solvers import ResidualFunction

REPO = Path(__file__).resolve().parents[1]
VECTORS = REPO.parent / "shared" / "vectors"


@pytest.fixture(autouse=True)
def _float64_and_seed():
    torch.set_default_dtype(torch.float64)
    torch.manual_seed(0)
    yield


@pytest.fixture
def vectors_dir() -> Path:
    if not VECTORS.is_dir():
        pytest.skip(f"test vectors not found at {VECTORS} (shared/ must sit beside the repo)")
    return VECTORS


def run_fit_app(run_dir: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``experiments/fit.py`` in a subprocess with its run directory at ``run_dir``."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "experiments/fit.py", f"hydra.run.dir={run_dir}",
                           *overrides], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout)


class CountingResidual(ResidualFunction):
    """Records every parameter vector at which the residual is linearised."""

    def __init__(self, inner: ResidualFunction) -> None:
        super().__init__(inner.forward, inner.data, inner.noise_level, inner.gauge)
        self.points: list[torch.Tensor] = []

    def linearize(self, theta):
        self.points.append(theta.detach().clone())
        return super().linearize(theta)
