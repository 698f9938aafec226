"""Shared pytest fixtures and helpers: paths to the repo and the independent test vectors
(vendored under ``tests/data/vectors``), the fit app as a subprocess, a residual that
records its linearisation points."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Sequence

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


def distinct(points: list[torch.Tensor]) -> int:
    """How many different parameter vectors ``points`` holds (``torch.equal``)."""
    unique: list[torch.Tensor] = []
    for p in points:
        if not any(torch.equal(p, q) for q in unique):
            unique.append(p)
    return len(unique)


def timed_fit(problem, solver, config=None):
    """``(result, metrics, seconds)`` of Gauss-Newton or split Bregman on ``problem``, with
    the parameterisation's ``D`` (and TV groups)."""
    import time

    from torchfit.solvers import gauss_newton, split_bregman

    D = problem.parameterization.difference_operator()
    start = time.perf_counter()
    if solver is gauss_newton:
        result = gauss_newton(problem.residual(), problem.theta0, config, D=D)
    else:
        result = split_bregman(problem.residual(), problem.theta0, config, D=D,
                               groups=problem.parameterization.difference_groups())
    return result, problem.metrics(result.theta), time.perf_counter() - start


class CountingResidual(ResidualFunction):
    """Records every parameter vector at which the residual is linearised."""

    def __init__(self, inner: ResidualFunction) -> None:
        super().__init__(inner.forward, inner.data, inner.noise_level, inner.gauge)
        self.points: list[torch.Tensor] = []

    def linearize(self, theta):
        self.points.append(theta.detach().clone())
        return super().linearize(theta)


# -- a real TensorBoard server (what a user sees) ---------------------------------------------
TENSORBOARD = Path(sys.executable).with_name("tensorboard")


class TensorBoardServer:
    """``tensorboard --logdir <logdir> --port <free port>`` (default loader: the Rust data
    server) as a subprocess, read through its HTTP data API as the dashboard does."""

    def __init__(self, logdir: Path, startup_timeout: float = 120.0) -> None:
        import socket

        self.logdir = Path(logdir)
        with socket.socket() as s:
            s.bind(("localhost", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://localhost:{self.port}"
        self.log = self.logdir.parent / f"tensorboard-{self.port}.log"
        exe = str(TENSORBOARD) if TENSORBOARD.exists() else "tensorboard"
        with open(self.log, "wb") as out:
            # own session: stop() ends the server and its data-server child together
            self.proc = subprocess.Popen([exe, "--logdir", str(self.logdir), "--port",
                                          str(self.port)], stdout=out, stderr=subprocess.STDOUT,
                                         start_new_session=True)
        try:
            self.wait_until(lambda: self.get("/data/runs") is not None, startup_timeout,
                            "the server to answer")
        except BaseException:
            self.stop()
            raise

    def request(self, path: str, params: dict | None = None, body: object = None):
        """JSON of ``GET path?params`` (``POST`` with a JSON ``body``); ``None`` while the
        server does not answer."""
        import json
        import urllib.error
        import urllib.parse
        import urllib.request

        url = self.url + path + ("?" + urllib.parse.urlencode(params) if params else "")
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"}
                                     if data is not None else {})
        try:
            with urllib.request.urlopen(req, timeout=30) as response:
                return json.loads(response.read())
        except (urllib.error.URLError, ConnectionError) as e:
            if isinstance(e, urllib.error.HTTPError):
                raise AssertionError(f"{url}: HTTP {e.code}: {e.read()[:500]!r}") from None
            return None

    def get(self, path: str, **params):
        return self.request(path, params or None)

    def post(self, path: str, body: object):
        return self.request(path, None, body)

    def wait_until(self, predicate, timeout: float = 60.0, what: str = "the data"):
        """Poll ``predicate()`` until it is truthy (the data server loads files in the
        background, a few seconds after the first answer); returns its value."""
        import time

        deadline = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                raise AssertionError(f"tensorboard exited ({self.proc.returncode}):\n"
                                     + self.log.read_text(errors="replace")[-3000:])
            value = predicate()
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"tensorboard at {self.url} not ready ({what}) after "
                                     f"{timeout:.0f} s:\n"
                                     + self.log.read_text(errors="replace")[-3000:])
            time.sleep(0.25)

    # -- the dashboards' requests -----------------------------------------------------
    def runs(self) -> list[str]:
        return self.get("/data/runs") or []

    def scalar_tags(self) -> dict[str, dict]:
        """``{run: {tag: ...}}`` of the Scalars dashboard."""
        return self.get("/data/plugin/scalars/tags") or {}

    def scalars(self, run: str, tag: str) -> list[tuple[int, float]]:
        """``(step, value)`` points of one scalar curve."""
        points = self.get("/data/plugin/scalars/scalars", run=run, tag=tag)
        return [(int(step), float(value)) for _, step, value in points]

    def image_tags(self) -> dict[str, dict]:
        return self.get("/data/plugin/images/tags") or {}

    def images(self, run: str, tag: str) -> list[dict]:
        """Image entries (``step``, ``query`` of the blob, ...) of one tag."""
        return self.get("/data/plugin/images/images", run=run, tag=tag) or []

    def image_bytes(self, entry: dict) -> bytes:
        import urllib.request

        with urllib.request.urlopen(f"{self.url}/data/plugin/images/individualImage?"
                                    f"{entry['query']}", timeout=30) as response:
            return response.read()

    def hparams_experiment(self) -> dict:
        """What the HParams dashboard asks first: the columns (settings and metrics)."""
        return self.post("/data/plugin/hparams/experiment",
                         {"experimentName": "", "includeMetrics": True,
                          "hparamsLimit": 1000}) or {}

    def hparams_session_groups(self, experiment: dict | None = None) -> list[dict]:
        """The rows of the HParams dashboard (one session group per run), with every
        setting and metric column of ``experiment``."""
        experiment = experiment or self.hparams_experiment()
        cols = [{"hparam": h["name"], "order": "ORDER_UNSPECIFIED", "includeInResult": True}
                for h in experiment.get("hparamInfos", [])]
        cols += [{"metric": m["name"], "order": "ORDER_UNSPECIFIED", "includeInResult": True}
                 for m in experiment.get("metricInfos", [])]
        body = {"experimentName": "", "allowedStatuses": [
            "STATUS_UNKNOWN", "STATUS_SUCCESS", "STATUS_FAILURE", "STATUS_RUNNING"],
            "colParams": cols, "startIndex": 0, "sliceSize": 1000, "includeMetrics": True}
        return (self.post("/data/plugin/hparams/session_groups", body) or {}).get(
            "sessionGroups", [])

    def stop(self) -> None:
        import signal

        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=10)


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


def explicit_and_autograd(problem, seed: int):
    """``problem``'s linearisations with explicit products and with autograd products (the
    reference) at ``theta0 + 0.3 * xi``, and random directions ``v`` (parameters) and ``w``
    (data): ``(theta, lin, reference, v, w)``."""
    g = torch.Generator().manual_seed(seed)
    theta = problem.theta0 + 0.3 * torch.randn(problem.theta0.shape, generator=g,
                                               dtype=torch.float64)
    explicit, autograd = problem.residual(), problem.residual(explicit_products=False)
    assert explicit.products is not None and autograd.products is None
    lin, reference = explicit.linearize(theta), autograd.linearize(theta)
    v = torch.randn(theta.shape, generator=g, dtype=torch.float64)
    w = torch.randn(lin.r.shape, generator=g, dtype=torch.float64)
    return theta, lin, reference, v, w
