"""One run: a problem, a solver and callbacks in; a run directory and a :class:`FitResult` out.

The same call serves a notebook, a test and the Hydra app (``experiments/fit.py`` is a thin
adapter over :func:`fit`); nothing here knows a Hydra type.

Run directory (``run_dir``; ``None``: no files at all, the fit still runs):

``result.json``
    final metrics (PROBLEMS.md), ``iterations``, ``wall_s``, ``factorizations``,
    ``solves`` (whole-run totals, a resumed run included), ``converged``,
    ``stop_reason``, ``status`` (``completed``), ``resumed_from_iteration`` (a resumed
    run), ``problem`` (sizes), ``config`` and ``history`` (one row per outer iteration).
``params.pt``, ``field.npy``
    fitted ``theta`` and field (byte-identical for identical runs); ``init=`` of a later
    run starts from ``params.pt`` (:func:`initial_theta`)).
``checkpoint.pt``
    after every outer iteration: ``theta``, the solver's :meth:`~torchfit.solvers.Solver.state_dict`,
    the iteration and the settings it belongs to; nothing time-dependent, so identical
    runs write identical bytes. ``history.jsonl`` beside it holds the per-iteration rows
    (wall times included). ``resume=True`` continues from them exactly: the same
    ``theta`` bit for bit, the same metrics, ``max_iter`` the budget of the whole run.
``tb/``
    TensorBoard events (:mod:`torchfit.reporting.tensorboard`); a resumed run adds the
    steps that were lost with the killed process and never repeats one.
PNGs
    ``field.png``, ``error_curves.png`` and, for 2-D fields, ``snapshots.png`` (and for
    meshes ``frame_errors.png``, ``sheet_frame<f>.png``, ``frames.npz``; for dynamic
    problems ``time_errors.png`` and ``frames_strip.png``).

Every input is checked before the first file is written (:class:`FitConfigError`,
:class:`RunDirectoryError`); a refused resume touches nothing of the earlier run.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .errors import ConfigurationError
from .linalg import set_threads
from .reporting.body import BodyOutputs
from .reporting.field_snapshots import FieldSnapshots
from .reporting.figures import field_is_chain, write_run_pngs
from .reporting.guard import PlotGuard
from .reporting.metrics import MetricsCallback
from .reporting.motion import MotionOutputs
from .reporting.progress import ProgressPrinter
from .reporting.results import (CHECKPOINT_FILE, PARAMS_FILE, RESULT_FILE, atomic_write,
                                jsonable, save_params, save_torch, write_json)
from .reporting.tensorboard import TensorBoardLogger
from .problems import InverseProblem
from .problems.base import (BodyProblem, FieldImageProblem, FramedProblem, MeshProblem,
                            MotionProblem)
from .records import IterationRecord, SolveResult
from .residual import warm_up_autograd
from .solvers import SOLVERS, Solver, SolverConfig

log = logging.getLogger("torchfit.fit")

HISTORY_FILE = "history.jsonl"
VERIFY_FILE = "verify.json"
CHECKPOINT_FORMAT = 2
#: Counters a result reports beside the metrics; ``objective_metric`` may name them too.
COUNT_KEYS = ("iterations", "wall_s", "factorizations", "solves")


class FitConfigError(ConfigurationError):
    """A setting of the run itself (not of the problem or solver) is invalid."""


class ResumeError(ConfigurationError):
    """The run directory's checkpoint cannot be continued with these settings."""


class RunDirectoryError(OSError):
    """The run directory cannot be written (the message names the path and the reason)."""


@dataclasses.dataclass
class FitOptions:
    """How a run reports itself (none of it changes the fit).

    Attributes:
        progress: one line per outer iteration through the ``torchfit.progress`` logger.
        log_every: TensorBoard scalars every ``n`` iterations (the last one always).
        snapshot_iterations: 2-D fields: field images after these iterations
            (``snapshots.png``, the seed's figure) and in TensorBoard.
        snapshot_every: also every ``n`` iterations in TensorBoard (0: only those).
        sheet_frame: frame whose deformed mesh is drawn (``None``: the problem's choice).
        threads: torch and BLAS threads of this process (0: leave as they are).
        objective_metric: the key of ``result.json`` that :attr:`FitResult.objective`
            returns (what a sweeper minimises).
        fold_hint: a 3-D body's warning about folded frames at the end suggests
            ``continuation=true`` (off in the stages of one, which report themselves).
    """

    progress: bool = True
    log_every: int = 1
    snapshot_iterations: Sequence[int] = (1, 5, 10, 40)
    snapshot_every: int = 10
    sheet_frame: int | None = None
    threads: int = 0
    objective_metric: str = "misfit"
    fold_hint: bool = True

    def check(self, problem: InverseProblem) -> None:
        """Raise :class:`FitConfigError` naming the first invalid option."""
        def need(ok: bool, message: str) -> None:
            if not ok:
                raise FitConfigError(message)

        need(isinstance(self.progress, bool), f"progress={self.progress!r} must be true or false")
        for key, low in (("log_every", 1), ("snapshot_every", 0), ("threads", 0)):
            value = getattr(self, key)
            need(isinstance(value, int) and not isinstance(value, bool) and value >= low,
                 f"{key}={value!r} must be an integer >= {low}")
        need(all(isinstance(i, int) and i >= 0 for i in self.snapshot_iterations),
             f"snapshot_iterations={list(self.snapshot_iterations)} must be integers >= 0")
        allowed = list(problem.metric_names()) + list(COUNT_KEYS)
        need(self.objective_metric in allowed,
             f"objective_metric={self.objective_metric} is not reported by {problem.name}; "
             f"choose one of {allowed}")
        if self.sheet_frame is not None:
            n = problem.n_frames if isinstance(problem, FramedProblem) else 0
            need(isinstance(self.sheet_frame, int) and n > 0 and -n <= self.sheet_frame < n,
                 f"sheet_frame={self.sheet_frame!r} is not a frame of {problem.name}"
                 + (f" (0..{n - 1})" if n else " (it has no frames to draw)"))


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        theta: ``(n_params,)`` fitted parameters; ``field`` the physical field.
        metrics: the final metrics of PROBLEMS.md.
        iterations, wall_s, factorizations, solves: whole-run totals (a resumed run
            included).
        converged, stop_reason: as the solver reports them.
        history: one row per outer iteration of the whole run (``iteration`` and every
            record scalar, metrics included).
        run_dir: the run directory (``None`` without files); ``files`` what was written.
        resumed_from: the iteration a resumed run continued after (``None``: fresh).
        solve: the solver's own result for this process's part of the run.
        first_stage: the first stage of a continuation
            (:func:`torchfit.continuation.fit_continued`), else ``None``.
    """

    theta: Tensor
    field: Tensor
    metrics: dict[str, float]
    iterations: int
    wall_s: float
    factorizations: int
    solves: int
    converged: bool
    stop_reason: str
    history: list[dict[str, float]]
    run_dir: Path | None = None
    files: list[Path] = dataclasses.field(default_factory=list)
    resumed_from: int | None = None
    solve: SolveResult | None = None
    first_stage: "FitResult | None" = None

    def value(self, key: str) -> float:
        """``metrics[key]`` or a count (``iterations``, ...); ``+inf`` where not finite, so
        that a sweeper ranks such a run last."""
        counts = {"iterations": self.iterations, "wall_s": self.wall_s,
                  "factorizations": self.factorizations, "solves": self.solves}
        value = float(self.metrics[key] if key in self.metrics else counts[key])
        return value if math.isfinite(value) else math.inf

    def summary(self) -> str:
        """One line: stop reason, iterations, time, counts and the headline metrics."""
        shown = ", ".join(f"{k} {self.metrics[k]:.3e}" for k in
                          ("misfit", "k_err_rel", "k_err_rel_aligned") if k in self.metrics)
        return (f"{self.stop_reason} after {self.iterations} iterations "
                f"({'converged' if self.converged else 'not converged'}) in {self.wall_s:.2f} s, "
                f"{self.factorizations} factorizations, {self.solves} solves: {shown}")


# -- solvers from names ---------------------------------------------------------------------
def solver_config(section: Mapping[str, Any] | SolverConfig | str) -> SolverConfig:
    """A validated solver config from a name, a mapping (``{'name': ..., settings}``) or a
    config object; :class:`~torchfit.solvers.SolverConfigError` names a bad setting."""
    if isinstance(section, SolverConfig):
        config = section
    else:
        values = {"name": section} if isinstance(section, str) else dict(section)
        name = values.get("name")
        if name not in SOLVERS:
            raise FitConfigError(f"solver={name!r} is not a solver; choose one of {sorted(SOLVERS)}")
        config_class = SOLVERS[name].config_class
        fields = {f.name for f in dataclasses.fields(config_class)}
        unknown = sorted(set(values) - fields)
        if unknown:
            raise FitConfigError(f"unknown setting(s) {['solver.' + u for u in unknown]} for "
                                 f"solver={name}; it has {sorted(fields - {'name'})}")
        config = config_class(**values)
    config.validate()
    return config


def build_solver(problem: InverseProblem, solver: Solver | SolverConfig | Mapping[str, Any] | str
                 ) -> Solver:
    """The solver for ``problem``: a :class:`~torchfit.solvers.Solver` as it is, or one built
    from a name/config with what its registry entry says it needs from the problem's
    parameterisation (the difference operator ``D`` and its TV groups)."""
    if isinstance(solver, Solver):
        return solver
    config = solver_config(solver)
    entry = SOLVERS[config.name]
    inputs: dict[str, Any] = {}
    if entry.takes_difference_operator(config) and not entry.needs_difference_operator(config):
        operator = getattr(problem.parameterization, "difference_operator", None)
        if operator is not None:
            inputs["D"] = operator()
    elif entry.needs_difference_operator(config):
        param = problem.parameterization
        operator = getattr(param, "difference_operator", None)
        if operator is None:
            raise FitConfigError(f"solver={config.name} needs the difference operator D of the "
                                 f"parameterisation, but {problem.name}'s "
                                 f"({type(param).__name__}) has none")
        inputs["D"] = operator()
        if entry.uses_groups(config):
            groups_of = getattr(param, "difference_groups", None)
            inputs["groups"] = groups_of() if groups_of is not None else None
    return entry.solver_class(config, **inputs)


# -- the starting point -----------------------------------------------------------------------
def initial_theta(problem: InverseProblem, init: Tensor | str | Path | None = None) -> Tensor:
    """Where the fit starts: ``problem.theta0`` (``init=None``), a given ``theta``, or the
    ``theta`` of an earlier run (its directory or its ``params.pt``).

    An earlier run is a start, not a resume: any problem and solver settings may differ
    (other frames, another mesh of the same body, another solver) as long as the
    parameterisation is the same: ``(n_params,)`` and, where ``params.pt`` records them, the
    field's name and transform. Raises :class:`FitConfigError` naming the file and what
    differs; nothing is read but that file.
    """
    if init is None:
        return problem.theta0.detach().clone()
    n = problem.parameterization.n_params
    where = "init"
    if isinstance(init, Tensor):
        theta = init.detach()
    else:
        path = Path(init).expanduser()
        if path.is_dir():
            path = path / PARAMS_FILE
        where = f"init={path}"
        if not path.is_file():
            raise FitConfigError(f"{where}: no such file; give the directory of a finished run "
                                 f"(it holds {PARAMS_FILE}) or the {PARAMS_FILE} itself")
        try:
            with open(path, "rb") as f:
                saved = torch.load(f, map_location="cpu", weights_only=True)
            theta = saved["theta"]
            if not isinstance(theta, Tensor):
                raise TypeError("its theta is not a tensor")
        except Exception as e:  # noqa: BLE001  (truncated, foreign or corrupt file)
            first = (str(e).strip().splitlines() or [type(e).__name__])[0][:120]
            raise FitConfigError(f"{where} is not a torchfit {PARAMS_FILE} ({first}); give the "
                                 "directory of a finished run") from None
        name = problem.parameterization.name
        for key, ours in (("field_name", problem.field_name),
                          ("transform", problem.parameterization.transform)):
            if key in saved and saved[key] != ours:
                raise FitConfigError(f"{where} holds a {name} with {key} {saved[key]!r}, but "
                                     f"{problem.name}'s is {ours!r}; start from a run of the "
                                     "same parameterisation")
    if theta.shape != (n,):
        raise FitConfigError(f"{where} has {tuple(theta.shape)} parameters, but {problem.name}'s "
                             f"parameterisation has ({n},); start from a run with the same "
                             "parameters (problem.parameters, problem.grid)")
    if not bool(torch.isfinite(theta).all()):
        bad = int(torch.nonzero(~torch.isfinite(theta))[0, 0])
        raise FitConfigError(f"{where}: parameter {bad} is {float(theta[bad])}; a start must "
                             "be finite")
    return theta.to(dtype=problem.theta0.dtype, device=problem.theta0.device).clone()


def _digest(theta: Tensor) -> str:
    """A short hash of ``theta``'s bytes (a checkpoint remembers where its run started)."""
    data = theta.detach().cpu().to(torch.float64).contiguous().numpy().tobytes()
    return hashlib.sha256(data).hexdigest()[:16]


# -- the run directory ------------------------------------------------------------------------
def check_writable(run_dir: Path) -> None:
    """Raise :class:`RunDirectoryError` if ``run_dir`` cannot be created or written (writes
    nothing)."""
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirectoryError(f"cannot write the run directory {run_dir}: it is a file")
    existing = run_dir
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise RunDirectoryError(f"cannot create the run directory {run_dir}: {existing} is a file")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise RunDirectoryError(f"cannot write the run directory {run_dir}: permission denied "
                                f"on {existing}")


def plain_settings(config: Any) -> dict[str, Any]:
    """Plain JSON values of a config dataclass or mapping (Enums as their values)."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    return jsonable(dict(config))


@dataclasses.dataclass
class _Resume:
    """What a checkpoint hands to the continued run."""

    iteration: int
    state: dict[str, Any]
    rows: list[dict[str, Any]]
    finished: bool
    stop_reason: str | None


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
                    start: Tensor | None = None) -> _Resume | None:
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
        raise ResumeError(f"cannot resume: {path} was written by an older torchfit (no solver "
                          "state); use another run directory or resume=false")
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
    started = None if start is None else _digest(start)
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
    return _Resume(iteration, state, rows, bool(payload.get("finished", False)),
                   payload.get("stop_reason"))


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


class _Checkpointer:
    """Callback committing the run's state after every outer iteration.

    ``history.jsonl`` gets the record's row first, then ``checkpoint.pt`` is replaced
    atomically: the checkpoint is the commit point, and a row past it is ignored on resume.
    """

    def __init__(self, run_dir: Path, problem: InverseProblem, solver: Solver,
                 rows: list[dict[str, Any]], start: Tensor | None = None) -> None:
        self.run_dir = run_dir
        self.solver = solver
        self.rows = rows
        self.fixed = {"format": CHECKPOINT_FORMAT, "problem": problem.name,
                      "problem_config": json.dumps(plain_settings(problem.cfg)),
                      "solver": solver.config.name,
                      "solver_config": json.dumps(_resumable(plain_settings(solver.config))),
                      "n_params": int(problem.theta0.numel()),
                      "init": None if start is None else _digest(start)}
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


# -- the run --------------------------------------------------------------------------------
def fit(problem: InverseProblem, solver: Solver | SolverConfig | Mapping[str, Any] | str, *,
        run_dir: str | Path | None = None, callbacks: Iterable[Callable[[IterationRecord], Any]] = (),
        resume: bool = False, options: FitOptions | None = None,
        config: Mapping[str, Any] | None = None,
        init: Tensor | str | Path | None = None) -> FitResult:
    """Fit ``problem`` with ``solver`` and write the run directory (module docstring).

    Args:
        problem: an inverse problem (``torchfit.problems``), built and checked.
        solver: a :class:`~torchfit.solvers.Solver`, or a solver name / config / mapping
            (:func:`build_solver` hands it the parameterisation's ``D`` where needed).
        run_dir: where the outputs go (created); ``None``: no files.
        callbacks: called with every :class:`~torchfit.records.IterationRecord` after the
            run's own (metrics are in ``record.extra``); returning ``True`` stops the fit.
        resume: continue from ``run_dir``'s checkpoint (a fresh start where there is none).
        options: :class:`FitOptions`.
        config: the settings to store in ``result.json`` and TensorBoard (the Hydra app's
            resolved config); default: the problem's and solver's settings.
        init: where to start instead of ``problem.theta0``: a ``theta`` or an earlier run
            (:func:`initial_theta`), e.g. the fit of the frames whose equilibrium is unique
            before all frames, or of a coarser mesh. A resume must repeat it.
    Returns:
        :class:`FitResult`.
    Raises:
        FitConfigError, ResumeError, :class:`~torchfit.problems.ProblemConfigError`,
        :class:`~torchfit.solvers.SolverConfigError`: a bad setting, before any file is
        written. RunDirectoryError: ``run_dir`` cannot be written (nothing written).
    """
    options = options or FitOptions()
    if not isinstance(problem, InverseProblem):
        raise FitConfigError(f"problem must be a torchfit InverseProblem, got "
                             f"{type(problem).__name__}")
    options.check(problem)
    solver = build_solver(problem, solver)
    start = None if init is None else initial_theta(problem, init)
    run_path = None if run_dir is None else Path(run_dir).resolve()
    if resume and run_path is None:
        raise FitConfigError("resume=True needs the run_dir of the run to continue")
    if run_path is not None:
        check_writable(run_path)
        if not resume and (run_path / CHECKPOINT_FILE).exists():
            raise FitConfigError(f"{run_path} already holds a run (its checkpoint.pt); resume=true "
                                 "continues it, or choose another run directory")
    restart = read_checkpoint(run_path, problem, solver, start) if resume and run_path else None
    if resume and run_path is not None and restart is None:
        log.warning("resume: %s has no checkpoint; starting from %s", run_path / CHECKPOINT_FILE,
                    "the initial guess" if init is None else "init")
    config = dict(config) if config is not None else {
        "problem": plain_settings(problem.cfg), "solver": plain_settings(solver.config)}
    if restart is not None and restart.finished and (run_path / RESULT_FILE).is_file() and not (
            restart.stop_reason == "max_iter" and solver.config.max_iter > restart.iteration):
        return _finished_result(problem, run_path, restart)   # a larger max_iter continues
    if options.threads > 0:
        set_threads(options.threads)
    # -- from here on files are written ---------------------------------------------------
    described = problem.describe()
    log.info("problem %s: %s parameters, %s data, noise level %s%s%s", described["name"],
             described["n_params"], described["n_data"], described["noise_level"],
             f"; starting from {init}" if start is not None and not isinstance(init, Tensor)
             else "", f"; resuming after iteration {restart.iteration}" if restart else "")
    rows: list[dict[str, Any]] = list(restart.rows) if restart else []
    chain: list[Callable[[IterationRecord], Any]] = [MetricsCallback(problem)]
    if options.progress:
        chain.append(ProgressPrinter())
    guard = PlotGuard()    # a failed drawing is warned about once, never fails the fit
    tb = snapshots = checkpointer = body = motion = None
    if run_path is not None:
        run_path.mkdir(parents=True, exist_ok=True)
        checkpointer = _Checkpointer(run_path, problem, solver, rows, start)
        chain.append(checkpointer)
        tb = TensorBoardLogger(run_path / "tb", log_every=options.log_every)
        if restart is not None:
            tb.resume(restart.rows, restart.iteration)
        else:
            tb.log_config(json.dumps(config, indent=2, default=str))
        chain.append(tb)
        if isinstance(problem, FieldImageProblem):
            snapshots = FieldSnapshots(problem, tb, run_path, list(options.snapshot_iterations),
                                       options.snapshot_every, options.sheet_frame, guard=guard)
            chain.append(snapshots)
        if isinstance(problem, BodyProblem):
            body = BodyOutputs(problem, tb, run_path, guard=guard,
                               suggest_continuation=options.fold_hint)
            chain.append(body)
        if isinstance(problem, MotionProblem):
            motion = MotionOutputs(problem, tb, run_path, list(options.snapshot_iterations),
                                   guard=guard)
            chain.append(motion)
    else:
        chain.append(lambda record: rows.append(record.row()))
    chain.extend(callbacks)
    warm_up_autograd()     # torch's lazy one-time set-up, outside the solver's clock
    try:
        solved = solver.solve(problem.residual(),
                              problem.theta0 if start is None else start, chain,
                              state=restart.state if restart else None)
    finally:
        if checkpointer is not None:
            checkpointer.close()
        if tb is not None:
            tb.flush()
    metrics = problem.metrics(solved.theta)
    field = problem.field(solved.theta)
    result = FitResult(solved.theta.detach(), field.detach(), metrics, solved.iterations,
                       solved.wall_time, solved.factorizations, solved.solves, solved.converged,
                       solved.stop_reason, rows, run_path, [],
                       restart.iteration if restart else None, solved)
    if run_path is not None:
        assert tb is not None and checkpointer is not None
        result.files = _write_outputs(problem, result, run_path, tb, snapshots, guard, config,
                                      body, motion)
        checkpointer.commit(solved.iterations, solved.theta, solver.state_dict(),
                            stop_reason=solved.stop_reason)
    return result


def _write_outputs(problem: InverseProblem, result: FitResult, run_dir: Path,
                   tb: TensorBoardLogger, snapshots: FieldSnapshots | None, guard: PlotGuard,
                   config: Mapping[str, Any], body: BodyOutputs | None = None,
                   motion: MotionOutputs | None = None) -> list[Path]:
    """Every file of a finished run; returns the pictures and data files written."""
    files = snapshots.finish() if snapshots is not None else []
    if motion is not None:
        files.extend(motion.finish(result.theta))
    comparison: dict[str, Any] = {}
    if body is not None:
        body_files, comparison = body.finish(result.theta)
        files.extend(body_files)
    final = {**result.metrics, "iterations": result.iterations, "wall_s": result.wall_s}
    hparams = {"problem": config.get("problem", {}), "solver": config.get("solver", {})}
    tb.finish(problem, result.theta, final, hparams, guard)
    files[:0] = list(save_params(run_dir, result.theta, result.field, problem.field_name,
                                 problem.parameterization.transform))
    if isinstance(problem, MeshProblem):
        _save_frames(run_dir / "frames.npz", problem, result.theta)
        files.append(run_dir / "frames.npz")
    summary = result_dict(problem, result, config)
    if comparison:
        summary["model_comparison"] = {"frame": comparison["frame"]}
        for material in ("homogeneous", "fitted"):
            summary["model_comparison"][material] = {
                name: {k: v for k, v in values.items() if not k.endswith("_per_frame")}
                for name, values in comparison[material].items()}
    write_json(run_dir / RESULT_FILE, summary)
    files[:0] = write_run_pngs(run_dir, problem, result.theta, result.history, guard,
                               field_is_chain(problem))
    return files


def result_dict(problem: InverseProblem, result: FitResult,
                config: Mapping[str, Any]) -> dict[str, Any]:
    """The content of ``result.json`` (module docstring)."""
    out: dict[str, Any] = {k: float(v) for k, v in result.metrics.items()}
    out.update({"iterations": result.iterations, "wall_s": result.wall_s,
                "factorizations": result.factorizations, "solves": result.solves,
                "converged": result.converged, "stop_reason": result.stop_reason,
                "status": "completed"})
    if result.resumed_from is not None:
        out["resumed_from_iteration"] = result.resumed_from
    out["problem"] = problem.describe()
    out["config"] = dict(config)
    out["history"] = result.history
    return out


def _finished_result(problem: InverseProblem, run_dir: Path, restart: _Resume) -> FitResult:
    """A resume of a run that had already finished: its result, nothing rewritten."""
    saved = json.loads((run_dir / RESULT_FILE).read_text(encoding="utf-8"))
    with open(run_dir / "params.pt", "rb") as f:
        params = torch.load(f, map_location="cpu", weights_only=True)
    metrics = {k: float(saved[k]) if saved[k] is not None else math.nan
               for k in problem.metric_names() if k in saved}
    log.info("resume: %s had already finished after iteration %d; nothing to do", run_dir,
             restart.iteration)
    return FitResult(params["theta"], params["field"], metrics, int(saved["iterations"]),
                     float(saved["wall_s"]), int(saved["factorizations"]), int(saved["solves"]),
                     bool(saved["converged"]), str(saved["stop_reason"]), restart.rows, run_dir,
                     [], restart.iteration)


def _save_frames(path: Path, problem: InverseProblem, theta: Tensor) -> None:
    """Rest points, cells, fitted (and true) positions of every frame of a mesh problem."""
    field = problem.field(theta)
    with torch.no_grad():
        x = problem.simulate(problem.simulation_input(theta)).detach().cpu().numpy()
    arrays = {"rest_points": problem.mesh.points, "cells": problem.mesh.cells, "positions": x,
              "field": field.detach().cpu().numpy()}
    if problem.x_true is not None:
        arrays["true_positions"] = problem.x_true.detach().cpu().numpy()

    def write(f) -> None:
        np.savez_compressed(f, **arrays)

    atomic_write(path, write)


# -- derivative verification ------------------------------------------------------------------
VERIFY_POINTS = ("initial", "truth")
#: The offset draws from ``seed + OFFSET_STREAM``: independent of the directions ``verify``
#: draws from ``seed``.
OFFSET_STREAM = 1_000_003


def verification_point(problem: InverseProblem, at: str = "initial", perturbation: float = 0.1,
                       seed: int = 0) -> Tensor:
    """``theta`` at the initial guess or the truth, plus a seeded Gaussian offset of relative
    size ``perturbation`` (additive on a log-field; scaled by ``|theta|`` otherwise)."""
    if at not in VERIFY_POINTS:
        raise FitConfigError(f"at={at!r} is not a point to verify at; choose one of "
                             f"{list(VERIFY_POINTS)}")
    if not (isinstance(perturbation, (int, float)) and math.isfinite(perturbation)
            and perturbation >= 0):
        raise FitConfigError(f"perturbation={perturbation!r} must be a finite number >= 0")
    if at == "initial":
        theta = problem.theta0.detach().clone()
    elif problem.field_true is None:
        raise FitConfigError(f"at=truth needs a true field, but {problem.name} has none (user "
                             "targets); use at=initial")
    else:
        theta = problem.true_theta().detach()
    if perturbation == 0:
        return theta
    generator = torch.Generator().manual_seed(int(seed) + OFFSET_STREAM)
    xi = torch.randn(theta.shape, generator=generator, dtype=torch.float64).to(theta)
    if str(getattr(problem.parameterization, "transform", "exp")) == "exp":
        scale = torch.ones_like(theta)
    else:
        rms = float(torch.linalg.vector_norm(theta)) / math.sqrt(max(theta.numel(), 1))
        scale = torch.where(theta != 0, theta.abs(), torch.full_like(theta, rms or 1.0))
    return theta + perturbation * scale * xi


def verify(problem: InverseProblem, *, run_dir: str | Path | None = None, at: str = "initial",
           perturbation: float = 0.1, seed: int = 0, taylor_tol: float = 0.05,
           dot_tol: float = 1e-10, fd_tol: float | None = None,
           config: Mapping[str, Any] | None = None):
    """Taylor, dot-product and finite-difference checks of ``problem``'s Jacobian at
    :func:`verification_point`; writes ``verify.json`` into ``run_dir`` (if given).

    Returns the :class:`~torchfit.verification.VerificationReport` (``passed``). Every
    setting is checked before anything is written (:class:`FitConfigError`). ``fd_tol``
    ``None``: the simulation's own resolution
    (:func:`~torchfit.verification.default_fd_tol`).
    """
    from .verification import verify as verify_residual

    for name, value in (("taylor_tol", taylor_tol), ("dot_tol", dot_tol), ("fd_tol", fd_tol)):
        if name == "fd_tol" and value is None:
            continue
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise FitConfigError(f"{name}={value!r} must be a finite number > 0")
    theta = verification_point(problem, at, perturbation, seed)
    run_path = None if run_dir is None else Path(run_dir).resolve()
    if run_path is not None:
        check_writable(run_path)
    report = verify_residual(problem.residual(), theta, seed=int(seed), taylor_tol=taylor_tol,
                             dot_tol=dot_tol, fd_tol=fd_tol)
    if run_path is not None:
        out: dict[str, Any] = report.to_dict()
        out["problem"] = problem.describe()
        out["point"] = {"at": at, "perturbation": float(perturbation),
                        "theta_norm": float(torch.linalg.vector_norm(theta))}
        out["config"] = dict(config) if config is not None else {
            "problem": plain_settings(problem.cfg)}
        run_path.mkdir(parents=True, exist_ok=True)
        write_json(run_path / VERIFY_FILE, out)
    return report


__all__ = ["FitConfigError", "FitOptions", "FitResult", "ResumeError", "RunDirectoryError",
           "build_solver", "check_writable", "fit", "initial_theta", "result_dict", "solver_config",
           "verification_point", "verify"]
