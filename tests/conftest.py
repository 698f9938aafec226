"""Shared pytest fixtures: paths to the repo and the independent test vectors."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

import torchfit  # noqa: F401  (sets float64 as the default dtype)

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
