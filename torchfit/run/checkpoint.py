"""Checkpoint and exact resume of a run.

``checkpoint.pt`` is written after every outer iteration: ``theta``, the solver's
:meth:`~torchfit.solvers.Solver.state_dict`, the problem's
:attr:`~torchfit.problems.InverseProblem.warm_starts` (what its next simulations
depend on: the equilibria a warm-started Newton starts from), the iteration and the
settings and start it belongs to, and a run with frames held out of the fit the state of
its validation (:meth:`.validation.ValidationTracker.state_dict`: the chosen iteration and
parameters so far, the validation problem's simulation state); nothing time-dependent, so
identical runs write identical bytes. A resume restores the simulation state before the solver re-linearises at the
checkpointed point, so the resumed process simulates exactly what the uninterrupted one
did. Checkpoints of another format are refused (one line).
``history.jsonl`` beside it holds the per-iteration rows (wall times included); a row is
written before its checkpoint, and the checkpoint is the commit point. ``resume=True``
continues from them exactly: the same ``theta`` bit for bit, the same metrics, ``max_iter``
the budget of the whole run; a refused resume (:class:`ResumeError`) touches nothing.
The checkpoint also records digests of the problem's input data
(:meth:`~torchfit.problems.InverseProblem.input_digests`: a body's tet mesh and animation),
and a resume on other data is refused naming what changed; so is a checkpoint whose
parameters, solver state, warm starts or validation state hold a NaN or an infinity
(:func:`first_non_finite`: a damaged file, or one written by hand). A body's run keeps its mesh
(``mesh.npz``, :func:`torchfit.problems.keep_mesh`); the app's resume builds the
problem on it (:func:`torchfit.problems.body.run_mesh.resumed_mesh`, handed to
:func:`torchfit.problems.build_problem`), so a resume needs no mesh cache. A directory that holds a run
(:func:`run_files`) but no readable ``checkpoint.pt`` is refused too: a resume never
starts over.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..errors import ConfigurationError
from ..problems import InverseProblem
from ..records import IterationRecord, SolveResult, StopReason
from ..reporting import CHECKPOINT_FILE, PARAMS_FILE, RESULT_FILE, jsonable, save_torch
from ..solvers import Solver
from .options import FitConfigError, plain_settings
from .result import FitResult
from .start import digest

log = logging.getLogger("torchfit.run")

HISTORY_FILE = "history.jsonl"
CHECKPOINT_FORMAT = 3      # 3: with the simulation state
#: What a resume that cannot continue tells the user (the same instruction every time: a
#: run without resume into the directory is refused too, since it holds a run).
NOT_CONTINUABLE = "this run cannot be continued: start it again in another run directory"


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
    validation: dict[str, Any] | None = None


def _read_rows(path: Path, last: int) -> list[dict[str, Any]]:
    """Rows of ``history.jsonl`` up to iteration ``last`` (a torn last line is dropped)."""
    rows: list[dict[str, Any]] = []
    if path.is_file():
        for line in path.read_bytes().splitlines():
            try:        # bytes that are not UTF-8 JSON end the readable rows, like a torn line
                row = json.loads(line.decode("utf-8"))
                iteration = int(row.get("iteration", -1))
            except (ValueError, TypeError, AttributeError):
                break
            if iteration <= last:
                rows.append(row)
    return rows


def read_checkpoint(run_dir: Path, problem: InverseProblem, solver: Solver,
                    start: Tensor | None = None) -> Resume | None:
    """The checkpoint of ``run_dir`` if it belongs to this problem, solver and start
    (``None``: the problem's ``theta0``); ``None`` when there is none;
    :class:`ResumeError` naming what differs otherwise."""
    path = run_dir / CHECKPOINT_FILE
    if not os.path.lexists(path):
        found = run_files(run_dir)
        if found:
            raise ResumeError(f"cannot resume: {path} is missing, but {run_dir} holds a run "
                              f"({', '.join(found)}); {NOT_CONTINUABLE}")
        return None
    if not path.is_file():
        raise ResumeError(f"cannot resume: {path} is not a file; {NOT_CONTINUABLE}")
    try:
        with open(path, "rb") as f:
            payload = torch.load(f, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001  (a truncated, foreign or corrupt file)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        raise ResumeError(f"cannot resume: {path} is not a readable checkpoint ({first}); "
                          f"{NOT_CONTINUABLE}") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        written = payload.get("format") if isinstance(payload, dict) else None
        raise ResumeError(f"cannot resume: {path} has checkpoint format {written!r}, this "
                          f"torchfit continues format {CHECKPOINT_FORMAT} only (an older one "
                          f"lacks the state an exact resume needs); {NOT_CONTINUABLE}")
    expected = {"problem": problem.name,
                "problem_config": json.dumps(plain_settings(problem.cfg)),
                "solver": solver.config.name,
                "solver_config": json.dumps(_resumable(plain_settings(solver.config)))}
    for key, value in expected.items():
        if payload.get(key) != value:
            saved = payload.get(key)
            raise ResumeError(f"cannot resume: {path} belongs to other {key.replace('_', ' ')} "
                              f"settings ({_difference(saved, value)}); repeat the first run's "
                              "settings, or start again in another run directory")
    started = None if start is None else digest(start)
    if payload.get("init") != started:
        def origin(digest: str | None) -> str:
            return "the initial guess" if digest is None else f"an init= start ({digest})"
        raise ResumeError(f"cannot resume: {path} belongs to a run that started from "
                          f"{origin(payload.get('init'))}, this one starts from "
                          f"{origin(started)}; repeat the first run's init, or start again in "
                          "another run directory")
    saved_inputs = payload.get("inputs")
    if saved_inputs is not None:           # checkpoints before inputs were recorded: unchecked
        now = problem.input_digests()
        changed = sorted(k for k in set(saved_inputs) | set(now)
                         if saved_inputs.get(k) != now.get(k))
        if changed:
            raise ResumeError(f"cannot resume: {path} belongs to a run on another "
                              f"{' and '.join(changed)} than this one builds ("
                              + "; ".join(f"{k}: {saved_inputs.get(k)} there, {now.get(k)} now"
                                          for k in changed)
                              + "); give the run the inputs it ran on (the same mesh cache "
                              "entry, problem.path), or start again in another run directory")
    bad = first_non_finite({k: payload.get(k) for k in CONTINUED})
    if bad is not None:
        raise ResumeError(f"cannot resume: {path} holds non-finite values ({bad}): a run "
                          "cannot continue from them (the file was damaged or written by hand); "
                          "start the run again in another run directory")
    iteration = int(payload["iteration"])
    rows = _read_rows(run_dir / HISTORY_FILE, iteration)
    if not rows or int(rows[-1]["iteration"]) != iteration:
        raise ResumeError(f"cannot resume: {run_dir / HISTORY_FILE} does not reach iteration "
                          f"{iteration} of the checkpoint; {NOT_CONTINUABLE}")
    state = payload["solver_state"]
    state["wall_time"] = float(rows[-1].get("wall_time", 0.0))
    return Resume(iteration, state, rows, bool(payload.get("finished", False)),
                  payload.get("stop_reason"), payload["simulation_state"],
                  payload.get("validation"))


#: The entries of a checkpoint a resume continues from: their floating-point tensors must
#: be finite (:func:`first_non_finite`; plain numbers such as a solver's ``inf`` "no residual
#: yet" are not checked).
CONTINUED = ("theta", "solver_state", "simulation_state", "validation")


def first_non_finite(value: Any, where: str = "") -> str | None:
    """Where the first floating-point or complex tensor in ``value`` (nested dicts, lists)
    holds a NaN or infinity: ``"solver_state/theta: 1 of 64 entries, entry 3 is nan"``;
    ``None`` where every one is finite."""
    if isinstance(value, Tensor):
        if not (value.is_floating_point() or value.is_complex()):
            return None
        bad = ~torch.isfinite(value)
        if not bool(bad.any()):
            return None
        flat = bad.reshape(-1)
        first = int(torch.nonzero(flat)[0, 0])
        return (f"{where}: {int(flat.sum())} of {flat.numel()} entries, entry {first} is "
                f"{value.reshape(-1)[first].item()}")
    items = value.items() if isinstance(value, dict) else \
        enumerate(value) if isinstance(value, (list, tuple)) else ()
    for key, item in items:
        found = first_non_finite(item, f"{where}/{key}" if where else str(key))
        if found is not None:
            return found
    return None


def check_fresh_start(run_dir: Path) -> None:
    """Raise :class:`~.options.FitConfigError` where a run without ``resume`` would overwrite
    the run of ``run_dir`` (its ``checkpoint.pt``, or without one the files of
    :func:`run_files`): resume it where the checkpoint can be read, else start again
    elsewhere (what :func:`read_checkpoint` says too)."""
    path = run_dir / CHECKPOINT_FILE
    if not os.path.lexists(path):
        found = run_files(run_dir)
        if found:
            raise FitConfigError(f"{run_dir} already holds a run ({', '.join(found)}) "
                                 f"without its {CHECKPOINT_FILE}; choose another run directory")
        return
    try:
        with open(path, "rb") as f:
            payload = torch.load(f, map_location="cpu", weights_only=True)
        readable = isinstance(payload, dict) and payload.get("format") == CHECKPOINT_FORMAT
    except Exception:  # noqa: BLE001  (a directory, a truncated, foreign or corrupt file)
        readable = False
    if readable:
        raise FitConfigError(f"{run_dir} already holds a run (its {CHECKPOINT_FILE}); "
                             "resume=true continues it, or choose another run directory")
    raise FitConfigError(f"{run_dir} already holds a run whose {CHECKPOINT_FILE} cannot be "
                         f"read; {NOT_CONTINUABLE}")


def run_files(run_dir: Path) -> list[str]:
    """The files of ``run_dir`` that show a run was there (a fresh start would overwrite
    them): ``result.json``, ``params.pt``, a ``history.jsonl`` with rows beyond the first.

    A history holding only iteration 0's row is a run killed before its first commit (the
    row is written before the checkpoint): nothing of it can be continued or lost, so it
    does not count (the run starts again, rewriting that row)."""
    found = [name for name in (RESULT_FILE, PARAMS_FILE) if os.path.lexists(run_dir / name)]
    history = run_dir / HISTORY_FILE
    if os.path.lexists(history) and not history.is_file() or \
            history.is_file() and _has_rows_after_the_first(history):
        found.append(HISTORY_FILE)
    return found


def _has_rows_after_the_first(history: Path) -> bool:
    with open(history, "rb") as f:
        lines = [line for line in f.read().split(b"\n") if line.strip()]
    return len(lines) > 1


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
                 rows: list[dict[str, Any]], start: Tensor | None = None,
                 validation: Any = None) -> None:
        self.run_dir = run_dir
        self.problem = problem
        self.solver = solver
        self.validation = validation        # a ValidationTracker, or None
        self.rows = rows
        self.fixed = {"format": CHECKPOINT_FORMAT, "problem": problem.name,
                      "problem_config": json.dumps(plain_settings(problem.cfg)),
                      "solver": solver.config.name,
                      "solver_config": json.dumps(_resumable(plain_settings(solver.config))),
                      "n_params": int(problem.theta0.numel()),
                      "init": None if start is None else digest(start),
                      "inputs": dict(problem.input_digests())}
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
                   "simulation_state": _cpu(self.problem.warm_starts.warm_start_state()),
                   "finished": stop_reason is not None, "stop_reason": stop_reason}
        if self.validation is not None:
            payload["validation"] = _cpu(self.validation.state_dict())
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


def finished_outputs_readable(run_dir: Path) -> bool:
    """Whether a finished run's ``result.json`` (a JSON object) and ``params.pt`` (theta and
    field) can be read: then a resume returns them (:func:`finished_result`); otherwise it
    writes the outputs again from the checkpoint."""
    try:
        saved = json.loads((run_dir / RESULT_FILE).read_text(encoding="utf-8"))
        with open(run_dir / PARAMS_FILE, "rb") as f:
            params = torch.load(f, map_location="cpu", weights_only=True)
        return isinstance(saved, dict) and isinstance(params, dict) and all(
            isinstance(params.get(k), torch.Tensor) for k in ("theta", "field")) and all(
            k in saved for k in ("iterations", "wall_s", "factorizations", "solves",
                                 "converged", "stop_reason"))
    except Exception:  # noqa: BLE001  (missing, truncated, foreign or corrupt files)
        return False


def checkpointed_solve(restart: Resume) -> SolveResult:
    """The solver's outcome of a finished run, read from its checkpoint (no solver runs):
    the final ``theta``, iterations, stop reason and the run's clock and counters, for a
    resume that writes the outputs of a finished run again."""
    state = restart.state
    reason = StopReason(str(restart.stop_reason))
    converged = reason in (StopReason.discrepancy, StopReason.tolerance, StopReason.resolution,
                           StopReason.plateau)
    return SolveResult(state["theta"], converged, reason, restart.iteration, [],
                       float(state["wall_time"]), int(state["factorizations"]),
                       int(state["solves"]))


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
                     [], restart.iteration, validation=saved.get("validation"))
