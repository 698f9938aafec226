"""Continuation in the data: fit the frames far from a fold first, then all of them.

Where a body folds (tetrahedra turned inside out at equilibrium: the arm's inner elbow near
full bend), a frame has several equilibria, and which one Newton reaches depends on where
it starts. A fit of every frame from the homogeneous material can then stall with those
frames on other branches than the target's (``docs/notes/arm3d.md``, "Several
equilibria near full bend"), while the frames far from a fold pin the field down, and from
their fit the folded frames reach the target's branch. :func:`fit_continued` does that
continuation in one call (``continuation=true`` in the app):

1. simulate the start (the problem's initial guess or ``init``) cold from the animated
   pose, seeding no warm start, and find the frames **near a fold**: some tetrahedron
   compressed below ``min_volume`` of its rest volume (an inverted one included);
2. fit the other frames (``problem.with_frames``: the same targets on them, noise
   included) into ``<run_dir>/unique_frames/``, a complete run directory of its own;
3. fit every frame starting from that run's parameters (``init=``) into ``run_dir``.

The first stage gets ``first_max_iter`` iterations (default
``FIRST_STAGE_ITER_FACTOR`` times the solver's ``max_iter``): it must converge, since the
folded frames reach the target's equilibrium only from a field close to the truth (on the
arm from 3.1e-6, not from 2.2e-2), and its frames are the cheap ones (no fold); the solver's
own stopping rules end it earlier where it converges. The second stage gets ``max_iter``.

``continuation=auto`` (the app's default, :func:`continuation_setting`,
:func:`continuation_applies`) runs the continuation where it is known to pay: a body fitted
to targets simulated with its own model (``target=synthetic``: every frame, a folded one
included, has an equilibrium on its target), and then two stages only where some frame is
near a fold at the start. Targets the model does not reproduce (a rig, a user's frames) have
no such equilibrium for the folded frames: there it is one plain fit, with no fold check
(measured on the arm's rig targets: a reduction of 1.45 against 1.39 for several times the
cost, ``docs/notes/continuation.md``).

The second stage helps only where the folded frames reach the target's equilibrium from
the first stage's field; where they do not, it can move the field away from the truth, and
the first stage's result stays in its run directory (and ``first_stage``). Where no frame
is near a fold at the start, or every frame is, it is one plain :func:`~.fitting.fit`.
Both stages use the same solver settings (but the first stage's ``max_iter``) and options; a
``resume`` continues whichever stage was interrupted (a finished first stage is read back,
not refitted; the start and the first stage's last state are simulated again for their
fold checks). Figures: ``docs/notes/continuation.md``.
"""
from __future__ import annotations

import copy
import dataclasses
import logging
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np
import torch
from torch import Tensor

from ..problems import BodyProblem, InverseProblem, MotionProblem
from ..records import IterationRecord
from ..reporting import PARAMS_FILE, frame_spans
from ..solvers import Solver, SolverConfig
from .checkpoint import check_fresh_start
from .directory import check_writable
from .fitting import fit
from .lock import hold
from .options import FitConfigError, FitOptions, plain_settings
from .result import FitResult
from .solver import solver_config
from .start import initial_theta

log = logging.getLogger("torchfit.run")

#: The first stage's run directory, inside the run's.
FIRST_STAGE_DIR = "unique_frames"
#: Frames with a tetrahedron below this fraction of its rest volume at the start go last.
DEFAULT_MIN_VOLUME = 0.25
#: The first stage's iteration budget, in units of the solver's ``max_iter``.
FIRST_STAGE_ITER_FACTOR = 3


def continuation_setting(value: Any) -> bool | str:
    """The app's ``continuation`` setting checked: ``True``, ``False`` or ``"auto"``
    (module docstring); anything else raises :class:`~.options.FitConfigError`."""
    if isinstance(value, str) and value.lower() in ("true", "false", "auto"):
        return {"true": True, "false": False}.get(value.lower(), "auto")
    if not isinstance(value, bool):
        raise FitConfigError(f"continuation={value!r} must be true (frames far from a fold "
                             "first), false (one run) or auto (true for a synthetic target "
                             "with frames near a fold at the start)")
    return value


def first_stage_iterations(solver: SolverConfig, first_max_iter: Any) -> int:
    """The first stage's iteration budget: ``first_max_iter``, or ``None`` for
    ``FIRST_STAGE_ITER_FACTOR`` times ``solver.max_iter``; a bad value raises
    :class:`~.options.FitConfigError`."""
    if first_max_iter is None:
        return FIRST_STAGE_ITER_FACTOR * solver.max_iter
    if isinstance(first_max_iter, bool) or not isinstance(first_max_iter, int) \
            or first_max_iter < 0:
        raise FitConfigError(f"continuation_first_max_iter={first_max_iter!r} must be an "
                             "integer >= 0 (the first stage's iterations), or null for "
                             f"{FIRST_STAGE_ITER_FACTOR} times solver.max_iter")
    return first_max_iter


def continuation_applies(problem: InverseProblem) -> bool:
    """Whether ``continuation=auto`` considers the continuation: a quasistatic body fitted
    to an animation whose targets are simulated with its own model (it has a true field).
    Whether a frame is near a fold at the start is :func:`fit_continued`'s check. A body in
    time (``problem.dynamic=true``) is an initial-value problem: each step starts from the
    one before, so a material has one trajectory and no frame a choice of branches (what
    the continuation is for); ``continuation=true`` still runs it."""
    return isinstance(problem, BodyProblem) and not isinstance(problem, MotionProblem) \
        and problem.field_true is not None


def frames_near_fold(problem: InverseProblem, theta: Tensor, min_volume: float) -> list[int]:
    """Animation frame numbers of the fitted frames whose equilibrium at ``theta``
    (simulated cold, seeding no later warm start) compresses a tetrahedron below
    ``min_volume`` times its rest volume (inverted ones included)."""
    if not isinstance(problem, BodyProblem):
        raise FitConfigError(f"continuation=true needs a body fitted to an animation (arm3d, "
                             f"animation): {problem.name} has no frames that can fold; drop "
                             "continuation")
    return [n for n, r in _min_volume_ratios(problem, theta) if r < min_volume]


def _min_volume_ratios(problem: Any, theta: Tensor) -> list[tuple[int, float]]:
    """``(frame number, smallest volume ratio)`` of every fitted frame at ``theta``: an
    independent simulation (a state the problem holds already is found again)."""
    with torch.no_grad(), problem.warm_starts.independent():
        x = problem.simulate(problem.simulation_input(theta))
    ratios = np.asarray(problem.report.min_volume_ratio(x)).tolist()
    return list(zip(problem.frame_numbers(), ratios))


def fit_continued(problem: InverseProblem,
                  solver: Solver | SolverConfig | Mapping[str, Any] | str, *,
                  run_dir: str | Path | None = None,
                  callbacks: Iterable[Callable[[IterationRecord], Any]] = (),
                  resume: bool = False, options: FitOptions | None = None,
                  config: Mapping[str, Any] | None = None,
                  init: Tensor | str | Path | None = None,
                  min_volume: float = DEFAULT_MIN_VOLUME,
                  first_max_iter: int | None = None) -> FitResult:
    """:func:`~.fitting.fit` with the frames near a fold at the start fitted last
    (module docstring); the other arguments are :func:`~.fitting.fit`'s.

    Args:
        min_volume: a frame whose equilibrium at the start has a tetrahedron below this
            fraction of its rest volume is left to the second stage (0 < ``min_volume``
            < 1; raise it where the first stage's frames fold at its end, which the
            run's log reports).
        first_max_iter: the first stage's iteration budget (``None``:
            ``FIRST_STAGE_ITER_FACTOR`` times the solver's ``max_iter``); the second
            stage's is the solver's ``max_iter``.

    Returns:
        the second stage's :class:`~.result.FitResult` (every frame), with
        ``first_stage`` set to the first one's (``None`` where there was one stage).
        ``iterations``, ``wall_s`` and the counts are the second stage's; the first
        stage's are in its own ``result.json``.
    Raises:
        FitConfigError: the problem is not a body fitted to an animation, or a setting of
        :func:`~.fitting.fit` is bad (before any file is written).
    """
    callbacks = list(callbacks)
    if isinstance(min_volume, bool) or not isinstance(min_volume, (int, float)) \
            or not 0 < min_volume < 1:
        raise FitConfigError(f"continuation_min_volume={min_volume!r} must lie in (0, 1): the "
                             "fraction of its rest volume below which a compressed "
                             "tetrahedron marks its frame as near a fold")
    # a solver is built for one problem: each stage builds its own from the config
    solver = solver.config if isinstance(solver, Solver) else solver_config(solver)
    first_solver = dataclasses.replace(solver,
                                       max_iter=first_stage_iterations(solver, first_max_iter))
    start = initial_theta(problem, init)
    run_path = None if run_dir is None else Path(run_dir).resolve()
    if run_path is not None:
        check_writable(run_path)
    with hold(run_path):        # both stages: one run per directory (lock.py)
        return _fit_continued(problem, solver, first_solver, run_path, callbacks, resume,
                              options, config, init, start, float(min_volume))


def _fit_continued(problem: InverseProblem, solver: SolverConfig, first_solver: SolverConfig,
                   run_path: Path | None,
                   callbacks: list[Callable[[IterationRecord], Any]], resume: bool,
                   options: FitOptions | None, config: Mapping[str, Any] | None,
                   init: Tensor | str | Path | None, start: Tensor,
                   min_volume: float) -> FitResult:
    if run_path is not None:
        if not resume:
            check_fresh_start(run_path)
    # the stages report folds themselves: no end-of-run hint to use continuation=true
    options = dataclasses.replace(options or FitOptions(), fold_hint=False)
    options.check(problem)
    near_fold = frames_near_fold(problem, start, float(min_volume))
    numbers = problem.frame_numbers()
    unique = [n for n in numbers if n not in near_fold]
    if not near_fold or not unique:
        log.info("continuation: %s frame has a tetrahedron below %g of its rest volume at "
                 "the start; one run", "no" if not near_fold else "every", min_volume)
        result = fit(problem, solver, run_dir=run_path, callbacks=callbacks, resume=resume,
                     options=options, config=config, init=init)
        result.first_stage = None
        return result
    log.info("continuation: frames %s have a tetrahedron below %g of its rest volume at the "
             "start (near a fold); fitting the other %d frames first (at most %d iterations)%s",
             frame_spans(near_fold), min_volume, len(unique), first_solver.max_iter,
             f" ({run_path / FIRST_STAGE_DIR})" if run_path is not None else "")
    sub = problem.with_frames(unique)
    stage_dir = None if run_path is None else run_path / FIRST_STAGE_DIR
    first = fit(sub, first_solver, run_dir=stage_dir, callbacks=callbacks, resume=resume,
                options=options, init=init,
                config=_stage_config(config, sub, first_solver, unique, near_fold))
    folded = [n for n, r in _min_volume_ratios(sub, first.theta) if r <= 0]   # inverted
    if folded:
        log.warning("continuation: frames %s of the first stage have tetrahedra turned inside "
                    "out at its end, so they may sit on another equilibrium than the "
                    "target's; if the second stage stalls, raise continuation_min_volume "
                    "(now %g) to leave them to the second stage too", frame_spans(folded),
                    min_volume)
    del sub      # its simulations (one factorisation per frame) are not needed again
    log.info("continuation: all %d frames from the first stage's parameters (%s after %d "
             "iterations)", len(numbers), first.stop_reason, first.iterations)
    second_init: Tensor | Path = first.theta if stage_dir is None else stage_dir / PARAMS_FILE
    second_config = {**_run_config(config, problem, solver),
                     "continuation_first_stage": {"frames": unique, "near_fold": near_fold,
                                                  "run_dir": FIRST_STAGE_DIR}}
    result = fit(problem, solver, run_dir=run_path, callbacks=callbacks, resume=resume,
                 options=options, config=second_config, init=second_init)
    result.first_stage = first
    return result


def _run_config(config: Mapping[str, Any] | None, problem: InverseProblem,
                solver: SolverConfig) -> dict[str, Any]:
    """What a stage stores: the run's config (the app's), else the problem's and solver's
    settings (:func:`~.fitting.fit`'s default)."""
    if config is not None:
        return copy.deepcopy(dict(config))
    return {"problem": plain_settings(problem.cfg), "solver": plain_settings(solver)}


def _stage_config(config: Mapping[str, Any] | None, sub: InverseProblem, solver: SolverConfig,
                  unique: list[int], near_fold: list[int]) -> dict[str, Any]:
    """The first stage's stored config: the run's, with its frames and a note."""
    staged = _run_config(config, sub, solver)
    if isinstance(staged.get("problem"), dict):
        staged["problem"]["frames"] = list(unique)
    if isinstance(staged.get("solver"), dict):
        staged["solver"]["max_iter"] = solver.max_iter
    staged["continuation_stage"] = {"stage": 1, "frames": list(unique),
                                    "near_fold_left_for_stage_2": list(near_fold)}
    return staged
