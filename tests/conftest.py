"""The suite's fixtures: float64, a fixed seed and one torch (and BLAS) thread for every test,
the vendored test vectors, a real TensorBoard server. Helpers that tests import are in
``tests/helpers/``.

The tiers (tests/tiers.py): the fast tier's tests are marked ``fast``; the tests that must
run on one pytest-xdist worker get their ``xdist_group``; with ``TORCHFIT_TEST_SUMMARY`` set
(scripts/test.sh) the run's counts are written to that file."""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import pytest
import torch
from threadpoolctl import threadpool_limits

from helpers.tensorboard_server import TensorBoardServer
from helpers.vectors import VECTOR_FILES, VECTORS
from tiers import NOT_FAST, group_of, in_fast_tier, matches


def pytest_configure(config):
    config.addinivalue_line("markers", "fast: the fast tier, set from tests/tiers.py "
                            "(scripts/test.sh --tier fast)")


@pytest.hookimpl(tryfirst=True)     # before -m selects and before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        if in_fast_tier(item.nodeid, item.get_closest_marker("slow") is not None):
            item.add_marker(pytest.mark.fast)
        group = group_of(item.nodeid)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    if not config.args or config.args == ["tests"]:     # the whole suite was collected
        stale = [start for start in NOT_FAST if not any(matches(item.nodeid, start)
                                                        for item in items)]
        if stale:
            warnings.warn(pytest.PytestWarning(
                f"tests/tiers.py: NOT_FAST names no test: {', '.join(stale)} (renamed or "
                "gone: those tests are back in the fast tier; update the list)"))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """The counts of the run for scripts/test.sh's closing line (the controller's, under
    xdist): passed, failed (errors included), skipped."""
    path = os.environ.get("TORCHFIT_TEST_SUMMARY")
    if not path or hasattr(config, "workerinput"):
        return

    def count(*keys: str) -> int:
        return sum(1 for key in keys for report in terminalreporter.stats.get(key, [])
                   if getattr(report, "count_towards_summary", True))

    Path(path).write_text(f"{count('passed')} passed, {count('failed', 'error')} failed, "
                          f"{count('skipped')} skipped\n")


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
    # the BLAS and OpenMP pools of numpy and scipy too (OpenBLAS's threads spin): two pytest
    # workers with two BLAS threads each ask four cores of two
    with threadpool_limits(limits=1):
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
