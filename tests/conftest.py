"""The suite's fixtures: float64, a fixed seed and one torch thread for every test, the vendored
test vectors, a real TensorBoard server. Helpers that tests import are in ``tests/helpers/``."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from helpers.tensorboard_server import TensorBoardServer
from helpers.vectors import VECTOR_FILES, VECTORS


@pytest.fixture(autouse=True)
def _float64_and_seed():
    # torchfit leaves torch's default dtype alone (problems use their own dtype); the
    # tests' own ad-hoc tensors (torch.randn(n), torch.ones(n), ...) are float64.
    torch.set_default_dtype(torch.float64)
    torch.manual_seed(0)
    yield


@pytest.fixture(autouse=True)
def _one_torch_thread():
    # The tests' problems are small: torch's intra-op pool costs more than it gains on them,
    # and its spinning threads slow everything on an oversubscribed 2-core machine (the 96x24
    # membrane's 40 LM iterations: 157 s with 2 threads, 90 s with 1, 2026-12-02). A test of
    # threading sets its own count; the processes a test starts choose theirs.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def vectors_dir() -> Path:
    """:data:`VECTORS`; a missing file is a test failure, never a skip."""
    missing = [name for name in VECTOR_FILES if not (VECTORS / name).is_file()]
    if missing:
        pytest.fail(f"vendored test vectors missing from {VECTORS}: {', '.join(missing)}")
    return VECTORS


@pytest.fixture
def tensorboard_server():
    """``serve(logdir) -> TensorBoardServer``: a real ``tensorboard --logdir`` with default
    options on a free port; every server started is stopped at the end of the test."""
    servers: list[TensorBoardServer] = []

    def serve(logdir) -> TensorBoardServer:
        servers.append(TensorBoardServer(Path(logdir)))
        return servers[-1]

    yield serve
    for server in servers:
        server.stop()
