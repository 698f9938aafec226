"""A real ``tensorboard`` server (what a user sees), read through its HTTP data API."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

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
