"""One fit: a problem, a solver and callbacks in; a run directory and a :class:`FitResult` out.

The same call serves a notebook, a test and the Hydra app (``experiments/fit.py`` is a thin
adapter over :func:`fit`); nothing here knows a Hydra type. The run directory's files are
listed in :mod:`.outputs` and :mod:`.checkpoint`. Every input is checked before the first
file is written (:class:`~.options.FitConfigError`,
:class:`~.directory.RunDirectoryError`); a refused resume touches nothing of the earlier
run. A run holds its directory for its whole length (:mod:`.lock`: a second run into it
is refused at once), and removes the temporary files a killed writer left there.

The callbacks of a run, in order: the evaluator (:mod:`.evaluator`: the one simulation per
record, whose metrics it adds to ``record.extra``), the validation tracker where frames are
held out of the fit (:mod:`.validation`), the progress line, the checkpoint
commit, TensorBoard, the problem's own outputs (fed the evaluation), then the caller's; an
iteration is thus in the checkpoint before TensorBoard shows it. The end of the run reads
the last evaluation (:meth:`~.evaluator.Evaluator.final`) and reports what the data
determine (:mod:`.identifiability`, from the solver's last linearisation; one warning line
where they determine no material, whose outputs then keep the starting field and do not say
converged) and the posterior spread of the fitted numbers (:mod:`.uncertainty`), and warns in one line where many parameters ended on a bound.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from torch import Tensor

from ..errors import SimulationError
from ..linalg import set_threads
from ..problems import BodyProblem, InverseProblem, keep_mesh
from ..records import IterationRecord
from ..reporting import (CHECKPOINT_FILE, PARAMS_FILE, ProgressPrinter, RESULT_FILE,
                         remove_stale_temporaries)
from ..residual import warm_up_autograd
from ..solvers import Solver, SolverConfig, UnsimulatedStart
from .checkpoint import (Checkpointer, check_fresh_start, checkpointed_solve,
                         finished_outputs_readable, finished_result, read_checkpoint)
from .directory import check_writable
from .evaluator import Evaluator
from .identifiability import identify
from .uncertainty import compare_meshes, estimate
from .lock import hold
from .options import FitConfigError, FitOptions, plain_settings
from .outputs import RunOutputs
from .result import FitResult
from .solver import build_solver, check_start_in_bounds
from .start import initial_theta
from .validation import ValidationTracker

log = logging.getLogger("torchfit.run")


def fit(problem: InverseProblem, solver: Solver | SolverConfig | Mapping[str, Any] | str, *,
        run_dir: str | Path | None = None, callbacks: Iterable[Callable[[IterationRecord], Any]] = (),
        resume: bool = False, options: FitOptions | None = None,
        config: Mapping[str, Any] | None = None,
        init: Tensor | str | Path | None = None) -> FitResult:
    """Fit ``problem`` with ``solver`` and write the run directory (module docstring).

    Args:
        problem: an inverse problem (``torchfit.problems``), built and checked.
        solver: a :class:`~torchfit.solvers.Solver`, or a solver name / config / mapping
            (:func:`~.solver.build_solver` hands it the parameterisation's ``D`` where
            needed).
        run_dir: where the outputs go (created); ``None``: no files.
        callbacks: called with every :class:`~torchfit.records.IterationRecord` after the
            run's own (metrics are in ``record.extra``); returning ``True`` stops the fit.
        resume: continue from ``run_dir``'s checkpoint (a fresh start where the directory
            holds no run; :class:`~.checkpoint.ResumeError` where it holds one whose
            checkpoint is missing, unreadable or belongs to other settings or inputs).
        options: :class:`~.options.FitOptions`.
        config: the settings to store in ``result.json`` and TensorBoard (the Hydra app's
            resolved config); default: the problem's and solver's settings.
        init: where to start instead of ``problem.theta0``: a ``theta`` or an earlier run
            (:func:`~.start.initial_theta`), e.g. the fit of the frames whose equilibrium
            is unique before all frames, or of a coarser mesh. A resume must repeat it.
    Returns:
        :class:`~.result.FitResult`.
    Raises:
        FitConfigError, ResumeError, :class:`~torchfit.problems.ProblemConfigError`,
        :class:`~torchfit.solvers.SolverConfigError`: a bad setting, before any file is
        written. RunDirectoryError: ``run_dir`` cannot be written (nothing written).
        :class:`~.lock.RunLockedError`: another run holds ``run_dir`` (nothing written).
    """
    options = options or FitOptions()
    if not isinstance(problem, InverseProblem):
        raise FitConfigError(f"problem must be a torchfit InverseProblem, got "
                             f"{type(problem).__name__}")
    validation = problem.validation_problem()
    options.check(problem, validated=validation is not None)
    solver = build_solver(problem, solver)
    start = None if init is None else initial_theta(problem, init)
    check_start_in_bounds(solver, start, init)
    run_path = None if run_dir is None else Path(run_dir).resolve()
    if resume and run_path is None:
        raise FitConfigError("resume=True needs the run_dir of the run to continue")
    if run_path is not None:
        check_writable(run_path)
    with hold(run_path):        # one run per directory (lock.py), from the first check on
        return _fit(problem, solver, run_path, callbacks, resume, options, config, init, start,
                    validation)


def _fit(problem: InverseProblem, solver: Solver, run_path: Path | None,
         callbacks: Iterable[Callable[[IterationRecord], Any]], resume: bool,
         options: FitOptions, config: Mapping[str, Any] | None,
         init: Tensor | str | Path | None, start: Tensor | None,
         validation: InverseProblem | None = None) -> FitResult:
    if run_path is not None:
        if not resume:
            check_fresh_start(run_path)
    restart = read_checkpoint(run_path, problem, solver, start) if resume and run_path else None
    if resume and run_path is not None and restart is None:
        log.warning("resume: %s has no checkpoint; starting from %s", run_path / CHECKPOINT_FILE,
                    "the initial guess" if init is None else "init")
    config = dict(config) if config is not None else {
        "problem": plain_settings(problem.cfg), "solver": plain_settings(solver.config)}
    finished = restart is not None and restart.finished and not (
        restart.stop_reason == "max_iter" and solver.config.max_iter > restart.iteration)
    if finished:                                # (a larger max_iter continues the run)
        if finished_outputs_readable(run_path):
            return finished_result(problem, run_path, restart)
        # killed while writing them, or damaged since: the checkpoint has the final state
        log.warning("resume: %s finished after iteration %d, but its %s or %s is missing or "
                    "damaged; writing its outputs again from the checkpoint", run_path,
                    restart.iteration, RESULT_FILE, PARAMS_FILE)
    if options.threads > 0:
        set_threads(options.threads)
    # -- from here on files are written ---------------------------------------------------
    if run_path is not None:
        for path in remove_stale_temporaries(run_path):
            log.warning("removed %s, left by a writer that was killed", path)
    try:
        described = problem.describe()      # a body simulates its start here
    except SimulationError as error:
        raise _unsimulated_start(problem, start, UnsimulatedStart(
            f"the fit's start cannot be simulated: {' '.join(str(error).split())}")) from error
    log.info("problem %s: %s parameters, %s data, noise level %s%s%s", described["name"],
             described["n_params"], described["n_data"], described["noise_level"],
             f"; starting from {init}" if start is not None and not isinstance(init, Tensor)
             else "", f"; resuming after iteration {restart.iteration}" if restart else "")
    rows: list[dict[str, Any]] = list(restart.rows) if restart else []
    evaluator = Evaluator(problem, validation)
    chain: list[Callable[[IterationRecord], Any]] = [evaluator]
    tracker = None
    if validation is not None:
        tracker = ValidationTracker(problem, validation, lambda: evaluator.last,
                                    options.validation_patience)
        if restart is not None and restart.validation is not None:
            tracker.load_state_dict(restart.validation, restart.iteration)
        chain.append(tracker)
    if options.progress:
        chain.append(ProgressPrinter())
    checkpointer = outputs = None
    if run_path is not None:
        run_path.mkdir(parents=True, exist_ok=True)
        if isinstance(problem, BodyProblem):   # a resume or simulate needs no mesh cache
            keep_mesh(problem, run_path)
        checkpointer = Checkpointer(run_path, problem, solver, rows, start, tracker)
        chain.append(checkpointer)
        outputs = RunOutputs(run_path, problem, evaluator, options, config, restart)
        chain.extend(outputs.callbacks())
    else:
        chain.append(lambda record: rows.append(record.row()))
    chain.extend(callbacks)
    warm_up_autograd()     # torch's lazy one-time set-up, outside the solver's clock
    if restart is not None:
        # the equilibria the checkpointed process's next simulations start from
        problem.warm_starts.restore_warm_start_state(restart.simulation, problem.device)
    try:
        try:
            solved = checkpointed_solve(restart) if finished else \
                solver.solve(problem.residual(), problem.theta0 if start is None else start,
                             chain, state=restart.state if restart else None)
        except UnsimulatedStart as error:
            raise _unsimulated_start(problem, start, error) from error
    finally:
        if checkpointer is not None:
            checkpointer.close()
        if outputs is not None:
            outputs.flush()
    # the solver's state as it ended: the counters of what follows (the final evaluation,
    # the identifiability report, the outputs) are not the run's
    final_state = None if finished else solver.state_dict()
    final = evaluator.final(solved.theta)
    if validation is not None:
        cost = evaluator.validation_cost
        failed = [iteration for iteration, _ in evaluator.validation_failures]
        log.info("validation: %d simulations of the held-out frames (%d factorizations, %d "
                 "solves, %.1f s) besides the fit%s", evaluator.validation_simulations,
                 cost["factorizations"], cost["solves"], cost["seconds"],
                 f"; {len(failed)} failed (iterations {failed}: NaN errors)" if failed else "")
    stop_reason = str(solved.stop_reason) if tracker is None else \
        tracker.stop_reason(str(solved.stop_reason))
    result = FitResult(solved.theta.detach(), final.field, final.metrics, solved.iterations,
                       solved.wall_time, solved.factorizations, solved.solves, solved.converged,
                       stop_reason, rows, run_path, [],
                       restart.iteration if restart else None, solved,
                       validation=None if tracker is None else tracker.summary(final))
    if result.validation is not None:
        result.validation["failed_iterations"] = [i for i, _ in evaluator.validation_failures]
    # init= an earlier fit: its misfit reduction from the start proves nothing
    result.identifiability = identify(problem, getattr(solver, "lin", None), solved.theta,
                                      final.metrics, rows, own_start=start is None)
    # every number with its uncertainty (uncertainty.py), from the same linearisation
    result.uncertainty = estimate(problem, getattr(solver, "lin", None), solved.theta,
                                  determined=result.identifiability.parameter_determined)
    if isinstance(problem, BodyProblem) and getattr(problem.cfg, "mesh_check", False) and \
            result.identifiability.determined:
        result.uncertainty.mesh_check = mesh_check(problem, solver, options, result)
    if not result.identifiability.determined:
        log.warning("%s", result.identifiability.warning())
        final = keep_the_start(result, evaluator, problem.theta0 if start is None else start)
    on_bounds = bound_warning(problem, rows)
    if on_bounds:
        log.warning("%s", on_bounds)
    if run_path is not None:
        assert outputs is not None and checkpointer is not None
        result.files = outputs.finish(result, final)
        if tracker is not None:
            result.files.append(tracker.write_params(run_path, solved.theta))
        if final_state is not None:     # (a finished run's checkpoint is final already)
            checkpointer.commit(solved.iterations, solved.theta, final_state,
                                stop_reason=stop_reason)
    return result


def _unsimulated_start(problem: InverseProblem, start: Tensor | None,
                       error: UnsimulatedStart) -> UnsimulatedStart:
    """``error`` naming what sets the start: ``init=``, or the problem's start settings."""
    source = "init=" if start is not None else \
        f"{', '.join(problem.start_settings())} (or init=)"
    return UnsimulatedStart(f"{error}; the start is set by {source}")


def keep_the_start(result: FitResult, evaluator: Evaluator, start: Tensor) -> Any:
    """An undetermined fit's outputs: the data do not see the directions its steps took, so
    the fitted field is the one it started from (``start``), evaluated, and the run does not
    say converged; returns that evaluation (the outputs' ``final``)."""
    final = evaluator.final(start.detach())
    result.theta, result.field, result.metrics = start.detach(), final.field, final.metrics
    result.converged = False
    result.kept_start = True
    return final


def mesh_check(problem: BodyProblem, solver: Solver, options: FitOptions,
               result: FitResult) -> dict[str, Any]:
    """``problem.mesh_check``: the same fit on a second mesh of the surface, no files
    (:func:`.uncertainty.compare_meshes`); one log line with its regions and cost."""
    def refit(other: InverseProblem) -> tuple[Tensor, dict[str, Any]]:
        log.info("mesh check: the fit again on a second mesh (%d tetrahedra)",
                 len(other.mesh.cells))
        again = fit(other, solver.config, options=dataclasses.replace(options, progress=False))
        return again.field, {"wall_s": again.wall_s, "iterations": again.iterations,
                             "factorizations": again.factorizations, "solves": again.solves}

    check = compare_meshes(problem, result.field, refit)
    log.info("mesh check (%d against %d tetrahedra, %.1f s): %s", *check["tets"],
             check["cost"]["seconds"], ", ".join(
                 f"{name} {100 * v['difference']:+.1f} %" for name, v in check["regions"].items()))
    return check


def bound_warning(problem: InverseProblem, rows: list[dict[str, Any]]) -> str | None:
    """The problem's line on the parameters that ended on a bound (the last record's
    ``at_lower_bound``, ``at_upper_bound``), or ``None``."""
    if not rows or "at_lower_bound" not in rows[-1] or not isinstance(problem, BodyProblem):
        return None
    return problem.report.bound_warning(int(rows[-1]["at_lower_bound"]),
                                 int(rows[-1].get("at_upper_bound", 0)))
