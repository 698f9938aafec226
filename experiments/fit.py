"""Fit a problem's material field with a solver (the main Hydra job of torchfit).

Usage (from the repository root)::

    python experiments/fit.py                                   # spring1d, Gauss-Newton
    python experiments/fit.py problem.noise=1e-4 solver=levenberg_marquardt
    python experiments/fit.py --cfg job                         # show the resolved config
    python experiments/fit.py -m hydra/launcher=joblib problem.noise=0,1e-4,1e-3 \
        solver=gauss_newton,levenberg_marquardt                 # sweep, one job per process
    python experiments/fit.py -m experiment=seed_table          # a sweep preset (conf/experiment/)

Outputs, in the Hydra run directory (``outputs/<problem>/<solver>/<time>/`` by default;
one directory per job under ``multirun/`` for ``-m``):

* ``result.json``: final metrics of PROBLEMS.md, iterations, wall seconds,
  factorisations, solves, converged flag, stop reason, problem sizes, the resolved
  config and the per-iteration history (see :mod:`torchfit.logging.results`);
* ``params.pt`` (``theta`` and the field), ``field.npy``;
* ``field.png`` (a 2-D field: truth / fit / aligned error with colour bars; a chain: ``k``
  per cell, truth and fit) and ``error_curves.png`` (misfit, ``k_err_rel_aligned`` or
  ``k_err_rel``, and ``tv`` for Split Bregman, against the iteration), see
  :mod:`torchfit.logging.pictures`; a picture that fails is warned about once, the fit
  goes on;
* for a 2-D field (poisson2d, membrane2d): ``snapshots.png`` (the field after the
  iterations ``snapshot_iterations``, default 1, 5, 10, 40; for membrane2d beside the
  per-frame position error); for membrane2d also ``frame_errors.png`` (per-frame error
  against the iteration), ``sheet_frame<f>.png`` (the deformed mesh of frame
  ``sheet_frame``) and ``frames.npz`` (rest points, cells, fitted and true positions of
  every frame);
* ``checkpoint.pt``: the parameters after the last outer iteration, rewritten every
  iteration;
* ``tb/``: TensorBoard events (tags in :mod:`torchfit.logging.tensorboard`): per-iteration
  scalars, field and error images every ``snapshot_every`` iterations and at the end,
  hparams (``problem.*``, ``solver.*`` against the final metrics, ``final/iterations``
  and ``final/wall_s`` among them);
* ``.hydra/`` and ``fit.log`` from Hydra.

Resume: re-run in the same directory with ``resume=true``::

    python experiments/fit.py hydra.run.dir=outputs/spring1d/gauss_newton/<time> resume=true

starts from the parameters of ``checkpoint.pt`` there (iteration numbers, TensorBoard
steps and the checkpoint continue the count; solver state such as the
Levenberg-Marquardt damping starts afresh). Hydra composes the config anew, so repeat
the first run's ``problem``/``solver`` overrides (a checkpoint of another size is
refused; changed problem settings are reported as a warning). Without a checkpoint it
starts from the problem's initial guess.

Every setting is validated before any output is written; an invalid one prints
``error: <message>`` on standard error, removes the run directory if it holds only
Hydra's own files, and exits with status 2, as does a config that Hydra cannot compose
(an unknown option such as ``problem=nope``, a misspelt or mistyped override). In a
multirun (``-m``) an invalid job does the same but returns ``+inf`` instead of exiting, so
that the sweep's other jobs still run. The task function returns the value a sweeper
minimises: the key ``objective_metric`` of ``result.json`` (default ``misfit``; e.g.
``objective_metric=k_err_rel_aligned`` for the Optuna preset ``experiment=sb_tuning``), or
``+inf`` for an invalid job or a non-finite value (hydra-optuna-sweeper 1.3 aborts the
whole study on a NaN return; ``inf`` is simply the worst trial).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import shutil
import sys
from pathlib import Path
from typing import Any, Callable

# Import the package of this checkout even when it is run without being installed.
REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import matplotlib  # noqa: E402

matplotlib.use("Agg")   # pictures are files and TensorBoard images; never open a window
import hydra  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from omegaconf.errors import OmegaConfBaseException  # noqa: E402

import torchfit  # noqa: E402,F401  (float64 default)
from torchfit.config import register_configs  # noqa: E402
from torchfit.linalg import SingularMatrixError  # noqa: E402
from torchfit.linalg.threads import set_blas_threads  # noqa: E402
from torchfit.logging import (CheckpointWriter, FieldSnapshots, MetricsCallback,  # noqa: E402
                              PlotGuard, ProgressPrinter, TensorBoardLogger, field_is_chain,
                              load_checkpoint, save_params, supports_field_images, write_result,
                              write_run_pngs)
from torchfit.logging.results import CHECKPOINT_FILE, history_rows  # noqa: E402
from torchfit.physics.equilibrium import NewtonConvergenceError  # noqa: E402
from torchfit.problems import InverseProblem, build_problem  # noqa: E402
from torchfit.solvers import SOLVERS, SolveResult, check_difference_operator  # noqa: E402

register_configs()
log = logging.getLogger("fit")

#: Errors that mean "the settings are wrong", reported as one line without traceback.
SETUP_ERRORS = (ValueError, OmegaConfBaseException, SingularMatrixError, NewtonConvergenceError)


@dataclasses.dataclass
class Job:
    """Everything validated before the first output file is written."""

    config: dict[str, Any]
    problem: InverseProblem
    solver: Callable[..., SolveResult]
    solver_config: Any
    theta0: torch.Tensor
    start_iteration: int
    resumed: bool
    solver_inputs: dict[str, Any] = dataclasses.field(default_factory=dict)


def solver_config(section: dict[str, Any]) -> tuple[Callable[..., SolveResult], Any]:
    """Solver function and validated config dataclass of ``cfg.solver``."""
    name = section.get("name")
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; choose one of {sorted(SOLVERS)}")
    config_cls, solve = SOLVERS[name]
    fields = {f.name for f in dataclasses.fields(config_cls)}
    unknown = sorted(set(section) - fields)
    if unknown:
        raise ValueError(f"unknown setting(s) {unknown} for solver {name}")
    config = config_cls(**section)
    config.validate()
    return solve, config


def solver_inputs(solve: Callable[..., SolveResult], solver_name: str,
                  problem: InverseProblem, config: Any = None) -> dict[str, Any]:
    """Extra inputs of a solver beyond the residual: the TV difference operator ``D`` and
    its row groups for solvers marked ``needs_difference_operator`` (split Bregman; a
    callable mark is asked with the solver ``config``: Gauss-Newton and
    Levenberg-Marquardt need ``D`` only for ``preconditioner=difference``).

    ``D`` comes from the problem's parameterisation, never from the solver; raises
    ``ValueError`` naming the parameterisation when it has none or when it is empty.
    """
    needs = getattr(solve, "needs_difference_operator", False)
    if callable(needs):
        needs = config is not None and needs(config)
    if not needs:
        return {}
    param = problem.parameterization
    operator = getattr(param, "difference_operator", None)
    if operator is None:
        raise ValueError(f"solver={solver_name} needs the difference operator D of the "
                         f"parameterisation, but the {problem.name} parameterisation "
                         f"({type(param).__name__}) has none")
    D = operator()
    groups_of = getattr(param, "difference_groups", None)
    groups = groups_of() if groups_of is not None else None
    check_difference_operator(D, int(problem.theta0.numel()), groups)
    return {"D": D, "groups": groups}


def prepare(cfg: DictConfig, run_dir: Path) -> Job:
    """Resolve and validate the whole config; build problem and solver; read a checkpoint.

    Writes nothing. Raises one of :data:`SETUP_ERRORS` on an invalid setting.
    """
    config = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    assert isinstance(config, dict)
    if int(config["log_every"]) < 1:
        raise ValueError(f"log_every must be >= 1, got {config['log_every']}")
    if int(config["threads"]) < 0:
        raise ValueError(f"threads must be >= 0 (0: torch's default), got {config['threads']}")
    if int(config["snapshot_every"]) < 0:
        raise ValueError(f"snapshot_every must be >= 0 (0: only snapshot_iterations), got "
                         f"{config['snapshot_every']}")
    objective = str(config["objective_metric"])
    if objective not in OBJECTIVE_METRICS:
        raise ValueError(f"objective_metric={objective!r} is not a key of result.json; choose one "
                         f"of {list(OBJECTIVE_METRICS)}")
    if any(int(i) < 0 for i in config["snapshot_iterations"]):
        raise ValueError(f"snapshot_iterations must be >= 0, got {config['snapshot_iterations']}")
    if int(config["threads"]) > 0:
        # Parallel sweep jobs (joblib) should not each use every core; the same for the
        # BLAS/LAPACK of scipy (the banded backend), whose idle threads spin on a busy machine.
        torch.set_num_threads(int(config["threads"]))
        set_blas_threads(int(config["threads"]))
    problem_section = dict(config["problem"])
    solve, solver_cfg = solver_config(dict(config["solver"]))
    problem = build_problem(str(problem_section.get("name")), problem_section)
    n_frames = int(getattr(problem, "n_frames", 0) or 0)
    frame = config.get("sheet_frame")
    if frame is not None and n_frames and not -n_frames <= int(frame) < n_frames:
        raise ValueError(f"sheet_frame={frame} is not a frame of {problem.name} "
                         f"(0..{n_frames - 1})")
    theta0, start, resumed = problem.theta0, 0, False
    if config["resume"]:
        path = run_dir / CHECKPOINT_FILE
        if path.is_file():
            ckpt = load_checkpoint(path, problem.parameterization.n_params, problem.name)
            saved = ckpt.problem_config
            changed = sorted(k for k in set(saved) | set(problem_section)
                             if saved.get(k) != problem_section.get(k)) if saved else []
            if changed:
                log.warning("resuming from a checkpoint of different problem settings %s: "
                            "it is only the initial guess of this fit", changed)
            theta0 = ckpt.theta.to(problem.theta0)
            start, resumed = ckpt.iteration, True
        else:
            log.warning("resume=true but %s does not exist; starting from the initial guess",
                        path)
    if objective not in reported_metrics(problem):
        raise ValueError(f"objective_metric={objective} is not reported by {problem.name}; choose "
                         f"one of {reported_metrics(problem)}")
    inputs = solver_inputs(solve, str(config["solver"].get("name")), problem, solver_cfg)
    return Job(config, problem, solve, solver_cfg, theta0, start, resumed, inputs)


#: The numeric keys of result.json that ``objective_metric`` may name.
OBJECTIVE_METRICS = ("misfit", "u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel",
                     "k_err_rel_aligned", "iterations", "wall_s", "factorizations", "solves")


def reported_metrics(problem: InverseProblem) -> list[str]:
    """The keys of :data:`OBJECTIVE_METRICS` that ``problem`` reports (as
    :meth:`InverseProblem.metrics`: state errors need the true state, field errors the true
    field, the aligned error a scale-free problem)."""
    absent = set()
    if problem.x_true is None:
        absent |= {"u_err_inf", "u_err_2"}
    if problem.field_true is None:
        absent |= {"k_err_inf", "k_err_2", "k_err_rel", "k_err_rel_aligned"}
    if not problem.scale_free:
        absent.add("k_err_rel_aligned")
    return [key for key in OBJECTIVE_METRICS if key not in absent]


def objective_value(metrics: dict[str, float], result: SolveResult, key: str) -> float:
    """The task function's return value: ``metrics[key]`` or the solver count ``key``;
    ``+inf`` when it is not finite (so that a sweeper ranks the trial last)."""
    counts = {"iterations": result.iterations, "wall_s": result.wall_time,
              "factorizations": result.factorizations, "solves": result.solves}
    value = float(metrics[key] if key in metrics else counts[key])
    return value if math.isfinite(value) else math.inf


def report_invalid(message: str, run_dir: Path) -> None:
    """Report an invalid setting in one line and remove a run directory left empty."""
    print("error: " + " ".join(message.split()), file=sys.stderr, flush=True)
    remove_if_only_hydra(run_dir)


def remove_if_only_hydra(run_dir: Path) -> bool:
    """Delete ``run_dir`` if it holds nothing but ``.hydra/`` and ``*.log`` files."""
    if not run_dir.is_dir():
        return False
    for entry in run_dir.iterdir():
        if entry.name == ".hydra" and entry.is_dir():
            continue
        if entry.suffix == ".log" and entry.is_file():
            continue
        return False
    # Close Hydra's handler of <job>.log before deleting it (later jobs of a sweep in
    # this process get their own handlers from Hydra).
    for handler in list(logging.getLogger().handlers):
        filename = getattr(handler, "baseFilename", None)
        if filename and Path(filename).resolve().parent == run_dir.resolve():
            logging.getLogger().removeHandler(handler)
            handler.close()
    shutil.rmtree(run_dir, ignore_errors=True)
    return True


def run(job: Job, run_dir: Path) -> float:
    """Fit, write every output, return the objective (:func:`objective_value`)."""
    problem, config = job.problem, job.config
    described = problem.describe()
    log.info("problem %s: %s parameters, %s data, noise level %s%s", described["name"],
             described["n_params"], described["n_data"], described["noise_level"],
             f"; resuming from iteration {job.start_iteration}" if job.resumed else "")
    metrics_cb = MetricsCallback(problem)
    tb = TensorBoardLogger(run_dir / "tb", log_every=int(config["log_every"]),
                           step_offset=job.start_iteration)
    tb.log_config(OmegaConf.to_yaml(config))
    callbacks: list[Callable[..., Any]] = [metrics_cb]
    if config["progress"]:
        callbacks.append(ProgressPrinter(step_offset=job.start_iteration))
    callbacks.append(tb)
    snapshots = None
    guard = PlotGuard()     # a failed drawing is warned about once, never fails the fit
    if supports_field_images(problem):
        snapshots = FieldSnapshots(problem, tb, run_dir, config["snapshot_iterations"],
                                   int(config["snapshot_every"]), config.get("sheet_frame"),
                                   guard=guard)
        callbacks.append(snapshots)
    callbacks.append(CheckpointWriter(run_dir / CHECKPOINT_FILE, job.start_iteration,
                                      problem.name, config["problem"]))
    try:
        result = job.solver(problem.residual(), job.theta0, job.solver_config, callbacks,
                            **job.solver_inputs)
    except KeyboardInterrupt:
        tb.close()
        print(f"interrupted; continue with: python experiments/fit.py "
              f"hydra.run.dir={run_dir} resume=true (and the same overrides)",
              file=sys.stderr, flush=True)
        sys.exit(130)
    except BaseException:
        tb.close()
        raise

    metrics = problem.metrics(result.theta)
    hparams = {"problem": config["problem"], "solver": config["solver"]}
    pictures = snapshots.finish() if snapshots is not None else []
    final = {**metrics, "iterations": result.iterations, "wall_s": result.wall_time}
    tb.finish(problem, result.theta, final, hparams, guard)
    field = problem.field(result.theta)
    save_params(run_dir, result.theta, field, problem.field_name)
    if getattr(problem, "mesh", None) is not None:
        save_frames(run_dir / "frames.npz", problem, field)
        pictures.append(run_dir / "frames.npz")
    result_path = write_result(run_dir, result, metrics, described, config,
                               step_offset=job.start_iteration)
    pictures = write_run_pngs(run_dir, problem, result.theta,
                              history_rows(result.history, job.start_iteration), guard,
                              field_is_chain(problem)) + pictures
    plot = "".join(f" {p.name}," for p in pictures)

    summary = ", ".join(f"{k} {metrics[k]:.3e}" for k in ("misfit", "k_err_rel",
                                                           "k_err_rel_aligned") if k in metrics)
    print(f"{result.stop_reason} after {result.iterations} iterations "
          f"({'converged' if result.converged else 'not converged'}) in {result.wall_time:.2f} s, "
          f"{result.factorizations} factorizations, {result.solves} solves: {summary}")
    print(f"results: {result_path} (beside it: params.pt, field.npy,{plot} {CHECKPOINT_FILE})")
    print(f"tensorboard --logdir {(run_dir / 'tb').resolve()}", flush=True)
    return objective_value(metrics, result, str(config["objective_metric"]))


def save_frames(path: Path, problem: InverseProblem, field: torch.Tensor) -> None:
    """The simulated frames of a mesh problem: rest points, cells, fitted and true positions."""
    import numpy as np

    with torch.no_grad():
        x = problem.simulate(field).detach().cpu().numpy()
    arrays = {"rest_points": problem.mesh.points, "cells": problem.mesh.cells, "positions": x,
              "field": field.detach().cpu().numpy()}
    if problem.x_true is not None:
        arrays["true_positions"] = problem.x_true.detach().cpu().numpy()
    np.savez_compressed(path, **arrays)


_task_started = False


@hydra.main(config_path="../conf", config_name="fit", version_base="1.3")
def main(cfg: DictConfig) -> float:
    global _task_started
    _task_started = True
    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir).resolve()
    try:
        job = prepare(cfg, run_dir)
    except SETUP_ERRORS as e:
        report_invalid(str(e), run_dir)
        if hydra_cfg.mode == RunMode.MULTIRUN:
            # Let the sweep's other jobs run; inf, not NaN: hydra-optuna-sweeper 1.3 hands
            # the value to optuna's tell() and aborts the study on a NaN.
            return math.inf
        sys.exit(2)
    return run(job, run_dir)


if __name__ == "__main__":
    try:
        main()
    except SystemExit as exit_:
        # Hydra exits 1 when the config cannot be composed (unknown group option,
        # misspelt or mistyped override) before the task runs: a bad configuration too,
        # so the same status 2 as the settings rejected by the task (as experiments/verify.py).
        multirun = any(a in ("-m", "--multirun") for a in sys.argv[1:])
        if exit_.code == 1 and not _task_started and not multirun:
            print("error: invalid configuration (see Hydra's message above)", file=sys.stderr)
            sys.exit(2)
        raise
