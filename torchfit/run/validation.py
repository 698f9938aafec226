"""Validation of a run on frames held out of its fit: the chosen iteration, early stopping.

A problem with frames held out (a body's ``problem.validation_frames`` or
``problem.validation_every``, :mod:`torchfit.problems.body.held_out`) gives the run a second
problem on those frames (:meth:`~torchfit.problems.InverseProblem.validation_problem`). The
run's evaluator (:mod:`.evaluator`) simulates it at every recorded iteration, beside the
fitted frames' simulation (counted in ``Evaluator.validation_simulations``): its metrics
(:data:`VALIDATION_METRICS`) are in the evaluation (``Evaluation.validation``) and join the
record as ``validation/<key>``: history rows, ``result.json``'s ``history`` and the
TensorBoard tags ``validation/surface_err_mean``, ``validation/surface_err_reduction``, ...

:class:`ValidationTracker`, the callback right after the evaluator, keeps the iteration of
lowest ``validation/surface_err_mean`` (the *chosen* iteration; the first of equals) and its
parameters, and stops the fit (stop reason ``validation``, not converged) once
``validation_patience`` accepted iterations in a row brought no lower error (a rejected
step changes nothing and does not count; 0: never stop early). Its state is in every
checkpoint (``validation``), with the validation problem's simulation state, so a resumed
run chooses exactly as the uninterrupted one.

Files: ``params.pt`` stays the last iterate (what the solver reached; what ``init=`` and a
resume read by default), ``params_best_validation.pt`` holds the chosen iteration's
parameters in the same format (give it to ``init=`` or to a simulation of the material);
``result.json`` gets ``validation_iteration``, ``validation_surface_err_mean`` and
``validation_surface_err_reduction`` (at the chosen iteration; a sweep's table and
``objective_metric`` can use them) and a ``validation`` section (:meth:`summary`).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor

from ..problems import InverseProblem, parameter_meaning
from ..records import IterationRecord, StopReason
from ..reporting import Evaluation, save_torch

log = logging.getLogger("torchfit.run")

#: The validation frames' metrics a run records (``validation/<key>``), where reported.
VALIDATION_METRICS = ("surface_err_mean", "surface_err_max", "surface_err_reduction",
                      "inverted_tets")
#: What the chosen iteration is chosen by.
CRITERION = "surface_err_mean"
PREFIX = "validation/"
BEST_PARAMS_FILE = "params_best_validation.pt"
#: Keys of ``result.json`` (top level) and of :meth:`~.result.FitResult.value`.
RESULT_KEYS = ("validation_iteration", "validation_surface_err_mean",
               "validation_surface_err_reduction")
#: The fitted frames' metrics reported beside the validation's at the chosen iteration.
FITTED_KEYS = ("surface_err_mean", "surface_err_reduction")


def validation_metrics(metrics: Mapping[str, float]) -> dict[str, float]:
    """The :data:`VALIDATION_METRICS` of the validation problem's ``metrics``."""
    return {k: float(metrics[k]) for k in VALIDATION_METRICS if k in metrics}


def record_keys(validation: Mapping[str, float]) -> dict[str, float]:
    """The record entries (``validation/<key>``) of a validation evaluation."""
    return {PREFIX + k: v for k, v in validation.items()}


class ValidationTracker:
    """Record callback after the evaluator: the chosen iteration, early stopping (module
    docstring).

    Args:
        problem: the fitted problem (its field of the chosen ``theta``).
        validation: the validation problem (its simulation state goes in the checkpoint).
        evaluation: returns the evaluator's evaluation of the current record.
        patience: accepted iterations without a lower validation error before the fit
            stops (0: never).
    """

    def __init__(self, problem: InverseProblem, validation: InverseProblem,
                 evaluation: Any, patience: int) -> None:
        self.problem = problem
        self.validation = validation
        self.evaluation = evaluation
        self.patience = int(patience)
        self.best_iteration: int | None = None
        self.best_theta: Tensor | None = None
        self.best: dict[str, float] = {}
        self.fitted_at_best: dict[str, float] = {}
        self.stale = 0
        self.stopped = False
        self.resumed_through: int | None = None

    def __call__(self, record: IterationRecord) -> bool | None:
        if self.resumed_through is not None and record.iteration <= self.resumed_through:
            # the checkpoint's iteration, judged by the first process (which may have been
            # killed after deciding to stop, before the end of its run)
            return True if self.stopped else None
        evaluation: Evaluation = self.evaluation()
        metrics = evaluation.validation or {}
        error = metrics.get(CRITERION, math.nan)
        if math.isfinite(error) and (self.best_iteration is None or error < self.best[CRITERION]):
            self.best_iteration = record.iteration
            self.best_theta = record.theta.detach().cpu().clone()
            self.best = dict(metrics)
            self.fitted_at_best = {k: float(record.extra[k]) for k in FITTED_KEYS
                                   if k in record.extra}
            self.stale = 0
        elif record.accepted and record.iteration > 0:
            self.stale += 1
        if self.patience and self.stale >= self.patience:
            self.stopped = True
            log.info("validation: no lower validation error in %d iterations since iteration "
                     "%s; stopping the fit (the chosen parameters are in %s)", self.stale,
                     self.best_iteration, BEST_PARAMS_FILE)
            return True
        return None

    # -- checkpoint ---------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """What a checkpoint keeps (tensors and plain values)."""
        return {"best_iteration": self.best_iteration, "best_theta": self.best_theta,
                "best": dict(self.best), "fitted_at_best": dict(self.fitted_at_best),
                "stale": self.stale, "stopped": self.stopped,
                "simulation": self.validation.warm_starts.warm_start_state()}

    def load_state_dict(self, state: Mapping[str, Any], iteration: int) -> None:
        """Continue after the checkpoint of ``iteration`` (its record is not judged again)."""
        self.best_iteration = state["best_iteration"]
        self.best_theta = state["best_theta"]
        self.best = {k: float(v) for k, v in state["best"].items()}
        self.fitted_at_best = {k: float(v) for k, v in state["fitted_at_best"].items()}
        self.stale = int(state["stale"])
        self.stopped = bool(state["stopped"])
        self.validation.warm_starts.restore_warm_start_state(state["simulation"],
                                                             self.validation.device)
        self.resumed_through = int(iteration)

    # -- the end of the run ----------------------------------------------------------------
    def stop_reason(self, solver_reason: str) -> str:
        """``validation`` where this tracker stopped the fit, else the solver's reason."""
        return StopReason.validation.value if self.stopped else solver_reason

    def summary(self, final: Evaluation) -> dict[str, Any]:
        """``result.json``'s ``validation`` section: the frames, the chosen iteration and the
        validation metrics there and at the end, the fitted frames' there."""
        return {"frames": self.validation.frame_numbers(),
                "fitted_frames": self.problem.frame_numbers(),
                "iteration": self.best_iteration, "chosen": dict(self.best),
                "fitted_at_chosen": dict(self.fitted_at_best),
                "final": dict(final.validation or {}), "patience": self.patience,
                "stopped_early": self.stopped, "params": BEST_PARAMS_FILE}

    def write_params(self, run_dir: Path, final_theta: Tensor) -> Path:
        """``params_best_validation.pt`` (``params.pt``'s format) of the chosen iteration."""
        theta = self.best_theta if self.best_theta is not None else final_theta.detach().cpu()
        with torch.no_grad():
            field = self.problem.field(theta.to(self.problem.theta0))
        payload: dict[str, Any] = {"theta": theta.clone(), "field": field.detach().cpu().clone(),
                                   "field_name": self.problem.field_name}
        if self.problem.parameterization.transform is not None:
            payload["transform"] = self.problem.parameterization.transform
        payload["meaning"] = dict(parameter_meaning(self.problem))     # as params.pt's
        return save_torch(run_dir / BEST_PARAMS_FILE, payload)


def held_out_worse(section: Mapping[str, Any]) -> str | None:
    """The summary line's warning where the held-out frames end worse than with the
    homogeneous material (the final ``surface_err_reduction`` below 1: the fit does not carry
    over to frames it did not see), else ``None``."""
    reduction = section.get("final", {}).get("surface_err_reduction")
    if reduction is None or not float(reduction) < 1.0:
        return None
    return (f"the held-out frames are WORSE than with the homogeneous material "
            f"({float(reduction):.3g}x): the fitted material does not carry over to them")


def result_values(section: Mapping[str, Any]) -> dict[str, Any]:
    """The top-level ``result.json`` keys (:data:`RESULT_KEYS`) of a ``validation`` section."""
    chosen = section.get("chosen", {})
    return {"validation_iteration": section.get("iteration"),
            "validation_surface_err_mean": chosen.get("surface_err_mean"),
            "validation_surface_err_reduction": chosen.get("surface_err_reduction")}
