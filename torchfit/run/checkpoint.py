"""Checkpoint and exact resume of a run.

``checkpoint.pt`` is written after every outer iteration: ``theta``, the solver's
:meth:`~torchfit.solvers.Solver.state_dict`, the problem's
:meth:`~torchfit.problems.InverseProblem.simulation_state` (what its next simulations
depend on: the equilibria a warm-started Newton starts from), the iteration and the
settings and start it belongs to; nothing time-dependent, so identical runs write identical
bytes. A resume restores the simulation state before the solver re-linearises at the
checkpointed point, so the resumed process simulates exactly what the uninterrupted one
did. Checkpoints of another format are refused (one line).
``history.jsonl`` beside it holds the per-iteration rows (wall times included); a row is
written before its checkpoint, and the checkpoint is the commit point. ``resume=True``
continues from them exactly: the same ``theta`` bit for bit, the same metrics, ``max_iter``
the budget of the whole run; a refused resume (:class:`ResumeError`) touches nothing.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..errors import ConfigurationError
from ..problems import InverseProblem
from ..records import IterationRecord
from ..reporting.results import CHECKPOINT_FILE, PARAMS_FILE, RESULT_FILE, jsonable, save_torch
from ..solvers import Solver
from .options import plain_settings
from .result import FitResult
from .start import digest

log = logging.getLogger("torchfit.run")

HISTORY_FILE = "history.jsonl"
CHECKPOINT_FORMAT = 3      # 3: with the simulation state


class ResumeError(ConfigurationError):
    """The run directory's checkpoint cannot be continued with these settings."""


@dataclasses.dataclass
class Resume:
    """What a checkpoint hands to the continued run."""

    iteration: int
    state: dict[str, Any]
    rows: list[dict[str, Any]]
    finished: bool
    stop_reason: str | None
    simulation: dict[str, Any] = dataclasses.field(default_factory=dict)


def _read_rows(path: Path, last: int) -> list[dict[str, Any]]:
    """Rows of ``history.jsonl`` up to iteration ``last`` (a torn last line is dropped)."""
    rows: list[dict[str, Any]] = []
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                break
            if int(row.get("iteration", -1)) <= last:
                rows.append(row)
    return rows


def read_checkpoint(run_dir: Path, problem: InverseProblem, solver: Solver,
                    start: Tensor | None = None) -> Resume | None:
    """The checkpoint of ``run_dir`` if it belongs to this problem, solver and start
    (``None``: the problem's ``theta0``); ``None`` when there is none;
    :class:`ResumeError` naming what differs otherwise."""
    path = run_dir / CHECKPOINT_FILE
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as f:
            payload = torch.load(f, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001  (a truncated, foreign or corrupt file)
        raise ResumeError(f"cannot resume: {path} is not a readable checkpoint ({e}); "
                          "use another run directory or resume=false") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        written = payload.get("format") if isinstance(payload, dict) else None
        raise ResumeError(f"cannot resume: {path} has checkpoint format {written!r}, this "
                          f"torchfit continues format {CHECKPOINT_FORMAT} only (an older one "
                          "lacks the state an exact resume needs); use another run directory "
                          "or resume=false")
    expected = {"problem": problem.name,
                "problem_config": json.dumps(plain_settings(problem.cfg)),
                "solver": solver.config.name,
                "solver_config": json.dumps(_resumable(plain_settings(solver.config)))}
    for key, value in expected.items():
        if payload.get(key) != value:
            saved = payload.get(key)
            raise ResumeError(f"cannot resume: {path} belongs to other {key.replace('_', ' ')} "
                              f"settings ({_difference(saved, value)}); repeat the first run's "
                              "settings, or use another run directory or resume=false")
    started = None if start is None else digest(start)
    if payload.get("init") != started:
        def origin(digest: str | None) -> str:
            return "the initial guess" if digest is None else f"an init= start ({digest})"
        raise ResumeError(f"cannot resume: {path} belongs to a run that started from "
                          f"{origin(payload.get('init'))}, this one starts from "
                          f"{origin(started)}; repeat the first run's init, or use another run "
                          "directory or resume=false")
    iteration = int(payload["iteration"])
    rows = _read_rows(run_dir / HISTORY_FILE, iteration)
    if not rows or int(rows[-1]["iteration"]) != iteration:
        raise ResumeError(f"cannot resume: {run_dir / HISTORY_FILE} does not reach iteration "
                          f"{iteration} of the checkpoint; use resume=false")
    state = payload["solver_state"]
    state["wall_time"] = float(rows[-1].get("wall_time", 0.0))
    return Resume(iteration, state, rows, bool(payload.get("finished", False)),
                   payload.get("stop_reason"), payload["simulation_state"])


def _resumable(settings: dict[str, Any]) -> dict[str, Any]:
    """Solver settings that must match to continue (``max_iter`` may be raised)."""
    return {k: v for k, v in settings.items() if k != "max_iter"}


def _difference(saved: Any, now: Any) -> str:
    try:
        a, b = json.loads(saved), json.loads(now)
    except (TypeError, ValueError):
        return f"{saved!r} there, {now!r} now"
    if isinstance(a, dict) and isinstance(b, dict):
        keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        return ", ".join(f"{k}: {a.get(k)!r} there, {b.get(k)!r} now" for k in keys)
    return f"{a!r} there, {b!r} now"


class Checkpointer:
    """Callback committing the run's state after every outer iteration.

    ``history.jsonl`` gets the record's row first, then ``checkpoint.pt`` is replaced
    atomically: the checkpoint is the commit point, and a row past it is ignored on resume.
    """

    def __init__(self, run_dir: Path, problem: InverseProblem, solver: Solver,
                 rows: list[dict[str, Any]], start: Tensor | None = None) -> None:
        self.run_dir = run_dir
        self.problem = problem
        self.solver = solver
        self.rows = rows
        self.fixed = {"format": CHECKPOINT_FORMAT, "problem": problem.name,
                      "problem_config": json.dumps(plain_settings(problem.cfg)),
                      "solver": solver.config.name,
                      "solver_config": json.dumps(_resumable(plain_settings(solver.config))),
                      "n_params": int(problem.theta0.numel()),
                      "init": None if start is None else digest(start)}
        with open(run_dir / HISTORY_FILE, "w", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(jsonable(row)) + "\n")
        self._history = open(run_dir / HISTORY_FILE, "a", encoding="utf-8")

    def __call__(self, record: IterationRecord) -> None:
        row = record.row()
        self.rows.append(row)
        self._history.write(json.dumps(jsonable(row)) + "\n")
        self._history.flush()
        self.commit(record.iteration, record.theta, self.solver.state_dict())

    def commit(self, iteration: int, theta: Tensor, state: dict[str, Any],
               stop_reason: str | None = None) -> None:
        state = dict(state)
        state.pop("wall_time", None)        # time lives in history.jsonl: same runs, same bytes
        payload = {**self.fixed, "iteration": int(iteration),
                   "theta": theta.detach().cpu().clone(), "solver_state": _cpu(state),
                   "simulation_state": _cpu(self.problem.simulation_state()),
                   "finished": stop_reason is not None, "stop_reason": stop_reason}
        save_torch(self.run_dir / CHECKPOINT_FILE, payload)

    def close(self) -> None:
        self._history.close()


def _cpu(value: Any) -> Any:
    if isinstance(value, Tensor):
        return value.detach().cpu().clone()
    if isinstance(value, dict):
        return {k: _cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_cpu(v) for v in value]
    return value


def finished_result(problem: InverseProblem, run_dir: Path, restart: Resume) -> FitResult:
    """A resume of a run that had already finished: its result, nothing rewritten."""
    saved = json.loads((run_dir / RESULT_FILE).read_text(encoding="utf-8"))
    with open(run_dir / PARAMS_FILE, "rb") as f:
        params = torch.load(f, map_location="cpu", weights_only=True)
    metrics = {k: float(saved[k]) if saved[k] is not None else math.nan
               for k in problem.metric_names() if k in saved}
    log.info("resume: %s had already finished after iteration %d; nothing to do", run_dir,
             restart.iteration)
    return FitResult(params["theta"], params["field"], metrics, int(saved["iterations"]),
                     float(saved["wall_s"]), int(saved["factorizations"]), int(saved["solves"]),
                     bool(saved["converged"]), str(saved["stop_reason"]), restart.rows, run_dir,
                     [], restart.iteration)
