"""The one simulation of a run per recorded iteration (and at its end) that observers read.

:class:`Evaluator` is the first callback of a run: for every record it simulates the
problem once at ``record.theta`` (:class:`~torchfit.reporting.evaluation.Evaluation`:
field, state, metrics), adds the metrics to ``record.extra`` for the callbacks after it,
and hands the evaluation to every observer it feeds (:meth:`Evaluator.feed`). The record's
``theta`` is the point the solver has just linearised, and the equilibrium keeps its
solution (and factorisation) in its cache, so that simulation is a cache hit that costs no
factorisation and no solve; it also marks that solution as the most recently used, exactly
once per record, which the solver's next warm start and the cache's eviction then see (the
order of the run's simulations is part of what makes two runs bit-identical).
:attr:`Evaluator.simulations` counts the simulations made here; nothing else in a run but
the solver (and a 3-D body's model comparison, :meth:`Evaluator.other_model`) simulates.

With a validation problem (the frames held out of the fit, :mod:`.validation`), every
evaluation but a report's baseline also simulates it at ``theta`` (its own equilibria and
warm starts, apart from the fit's: the fit's iterates are unchanged), counted in
:attr:`Evaluator.validation_simulations`; its metrics are ``Evaluation.validation`` and join
the record as ``validation/<key>``. Its factorisations and solves are not the solver's: they
are taken out of the counters the solver reports (:mod:`torchfit.linalg.counters`) and kept
in :attr:`Evaluator.validation_cost`, so that a run's counts, and an exact resume's, are the
fit's alone. A validation simulation that fails (a
:class:`~torchfit.errors.SimulationError`: Newton or a time step that does not converge on
the held-out frames at this material) does not end the fit: the evaluation's validation
metrics are NaN (never chosen; an accepted iteration counts towards the patience), one
warning line names the iteration and the cause, and :attr:`Evaluator.validation_failures`
keeps them.
"""
from __future__ import annotations

import contextlib
import logging
import math
import time
from typing import Any, Callable

import torch
from torch import Tensor

from ..errors import SimulationError
from ..linalg import counting
from ..problems import InverseProblem
from ..records import IterationRecord
from ..reporting import Evaluation
from .validation import VALIDATION_METRICS, record_keys, validation_metrics

log = logging.getLogger("torchfit.run")


class Evaluator:
    """One :class:`~torchfit.reporting.evaluation.Evaluation` per record, for every observer.

    Attributes:
        last: the evaluation of the last record (``None`` before the first).
        simulations: how many times :meth:`evaluate` simulated the problem.
        validation: the problem on the frames held out of the fit, or ``None``.
        validation_simulations: how many times it was simulated.
        validation_cost: its ``factorizations``, ``solves`` and ``seconds``.
        validation_failures: ``(iteration, message)`` of every validation simulation that
            failed (its metrics NaN; the fit went on).
    """

    def __init__(self, problem: InverseProblem, validation: InverseProblem | None = None) -> None:
        self.problem = problem
        self.validation = validation
        self.last: Evaluation | None = None
        self.simulations = 0
        self.validation_simulations = 0
        self.validation_cost = {"factorizations": 0, "solves": 0, "seconds": 0.0}
        self.validation_failures: list[tuple[int | None, str]] = []

    def evaluate(self, theta: Tensor, record: IterationRecord | None = None, *,
                 independent: bool = False) -> Evaluation:
        """The problem at ``theta`` (one simulation, and one of the validation problem);
        ``independent``: a cold start that seeds no later warm start (a report's baseline,
        not validated)."""
        problem = self.problem
        theta = theta.detach()
        isolated = problem.warm_starts.independent() if independent else contextlib.nullcontext()
        with torch.no_grad(), isolated:
            field = problem.field(theta)
            state = problem.simulate(problem.simulation_input(theta)).detach()
        self.simulations += 1
        validation, per_frame = (None, None) if independent or self.validation is None else \
            self.validate(theta, None if record is None else record.iteration)
        return Evaluation(theta, field.detach(), state, problem.metrics(theta, state), record,
                          validation, per_frame)

    def validate(self, theta: Tensor, iteration: int | None = None) -> tuple[dict[str, float], Any]:
        """The validation problem's metrics at ``theta`` (one simulation of its frames) and
        its per-frame mean surface error ``(F_val,)`` (``None`` where it reports none); NaN
        metrics and ``None`` where the simulation fails (module docstring)."""
        problem = self.validation
        assert problem is not None
        start = time.perf_counter()
        with torch.no_grad(), counting(isolated=True) as cost:    # not the solver's work
            try:        # metrics may simulate too (a baseline)
                state = problem.simulate(problem.simulation_input(theta)).detach()
                metrics = validation_metrics(problem.metrics(theta, state))
                frame_errors = getattr(problem, "frame_errors", None)
                per_frame = None if frame_errors is None else \
                    frame_errors(state).get("surface_err_mean")
            except SimulationError as error:
                message = " ".join(str(error).split())
                self.validation_failures.append((iteration, message))
                log.warning("validation: the held-out frames could not be simulated at "
                            "iteration %s (%s); their errors are NaN there and the fit goes on",
                            "?" if iteration is None else iteration, message)
                metrics, per_frame = {k: math.nan for k in VALIDATION_METRICS}, None
        self.validation_cost["factorizations"] += cost.factorizations
        self.validation_cost["solves"] += cost.solves
        self.validation_cost["seconds"] += time.perf_counter() - start
        self.validation_simulations += 1
        return metrics, per_frame

    def __call__(self, record: IterationRecord) -> None:
        self.last = self.evaluate(record.theta, record)
        record.extra.update(self.last.metrics)
        if self.last.validation is not None:
            record.extra.update(record_keys(self.last.validation))
        return None

    def feed(self, observer: Callable[[Evaluation], Any]) -> Callable[[IterationRecord], Any]:
        """A record callback handing ``observer`` this evaluator's evaluation of the record
        (the evaluator must come before it in the callbacks)."""
        def callback(record: IterationRecord) -> Any:
            if self.last is None or self.last.record is not record:
                raise RuntimeError("an observer was called before the run evaluated its record")
            return observer(self.last)

        return callback

    def final(self, theta: Tensor) -> Evaluation:
        """The evaluation at the end of the run: the last record's when the run ended at its
        ``theta`` (no simulation), else a new one (a resumed run that recorded nothing)."""
        if self.last is not None and torch.equal(self.last.theta, theta.detach()):
            return self.last
        return self.evaluate(theta)

    def other_model(self, model: str, field: Tensor) -> Tensor:
        """A 3-D body's state ``(F, n, 3)`` with another constitutive ``model`` and ``field``
        (:meth:`~torchfit.problems.body.model_comparison.ModelComparison.simulate_model`, no gradient)."""
        return self.problem.comparison.simulate_model(model, field.detach())
