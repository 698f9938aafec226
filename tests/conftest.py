"""Shared pytest fixtures and helpers: paths to the repo and the independent test vectors
(vendored under ``tests/data/vectors``), the fit app as a subprocess, a residual that
records its linearisation points."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchfit.solvers import ResidualFunction

REPO = Path(__file__).resolve().parents[1]
#: The independent test vectors of PROBLEMS.md, vendored (committed) with the tests.
VECTORS = REPO / "tests" / "data" / "vectors"
#: Where they come from: ``shared/vectors`` beside the repository, when it is there.
SHARED_VECTORS = REPO.parent / "shared" / "vectors"
#: Every file the tests read from :data:`VECTORS`.
VECTOR_FILES = ("README.md", "poisson2d_N16_blocks.npz", "poisson2d_N16_ipam.npz",
                "spring1d_n64.npz")


@pytest.fixture(autouse=True)
def _float64_and_seed():
    # torchfit leaves torch's default dtype alone (problems use their own dtype); the
    # tests' own ad-hoc tensors (torch.randn(n), torch.ones(n), ...) are float64.
    torch.set_default_dtype(torch.float64)
    torch.manual_seed(0)
    yield


@pytest.fixture
def vectors_dir() -> Path:
    """:data:`VECTORS`; a missing file is a test failure, never a skip."""
    missing = [name for name in VECTOR_FILES if not (VECTORS / name).is_file()]
    if missing:
        pytest.fail(f"vendored test vectors missing from {VECTORS}: {', '.join(missing)}")
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
