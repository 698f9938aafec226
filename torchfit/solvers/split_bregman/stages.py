"""Split Bregman's stages: when a stage (a fixed ``mu``) ends, and the search over stages.

A stage is at its fixed point (:func:`at_fixed_point`) when the relative ADMM primal
residual is at most ``tol`` and the relative dual residual is too, or the objective
changed by at most ``tol^2`` (relative) over the last 10 iterations (``tol`` is
``stage_tol``, or ``bregman_tol`` in a data-Bregman run, which must also fit the data to
``tol ||r_0||``); or when nothing moves. A stage clearly above the discrepancy level ends
early (:meth:`StageSearch.out_of_reach`).

With a noise level ``delta`` (``staged``), :class:`StageSearch` walks ``mu_k = mu_0
growth^{+-k}`` from the first stage: towards weaker TV (larger ``mu``) until a stage fits,
``||r|| <= tau delta`` (``discrepancy``), or until a stage lowers the misfit of the one
before by less than ``spread = delta / sqrt(2m)`` (the spread of the noise's norm over
``m`` data): the stage before is returned (``plateau``); when the first stage already
fits, towards stronger TV, returning the strongest stage that still fits. At most
``max_stages`` stages. Without a noise level a stage's end is the run's end
(:func:`fixed_weight_stop`).

The search's memory (direction, the accepted stage's snapshot, a pending return and its
stop reason) is part of the solver's state dict.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

from ...records import StopReason
from ..base import Stop


def at_fixed_point(objectives: list[float], last: dict[str, Any], tol: float,
                   fits: bool) -> bool:
    """Whether the stage is at its fixed point after the accepted iteration ``last``
    (its ``primal``, ``primal_rel``, ``dual_rel`` and ``step_norm``; ``objectives`` ends
    with its objective); ``fits``: the misfit test of a data-Bregman run (else true)."""
    new_obj = objectives[-1]
    stagnant = len(objectives) > 10 and \
        abs(objectives[-11] - new_obj) <= tol ** 2 * abs(new_obj)
    if fits and last["primal_rel"] <= tol and (last["dual_rel"] <= tol or stagnant):
        return True
    return last["primal"] == 0.0 and last["step_norm"] == 0.0   # nothing moves


def fixed_weight_stop(status: str) -> Stop:
    """The end of a run without stages: a stage that ended with ``status``
    (``converged``, ``budget`` or ``stalled``)."""
    if status == "converged":
        return Stop(True, StopReason.tolerance)
    return Stop(False, StopReason.stalled if status == "stalled" else StopReason.max_iter)


class StageEnd(NamedTuple):
    """What follows a stage: the run's end (``stop``), a next stage with weight
    ``next_mu``, or neither: the return to the accepted stage is pending."""

    stop: Stop | None = None
    next_mu: float | None = None


class StageSearch:
    """The search over stages in ``mu`` (see the module docstring).

    Attributes:
        direction: ``None`` before the first stage ends, then ``'weaker'`` or
            ``'stronger'`` (TV).
        accepted: the solver's snapshot of the stage to return to (its ``norm``: the
            stage's misfit), or ``None``.
        restore_pending: the next outer iteration returns to ``accepted``.
        restore_reason: the stop reason of that return.
    """

    def __init__(self) -> None:
        self.direction: str | None = None
        self.accepted: dict[str, Any] | None = None
        self.restore_pending = False
        self.restore_reason = StopReason.discrepancy

    @staticmethod
    def out_of_reach(misfits: list[float], level: float, above_factor: float) -> bool:
        """The stage's misfit is above ``level`` by more than ``above_factor`` times its
        change over the last 10 accepted iterations: it will not get there."""
        return len(misfits) > 10 and misfits[-1] - level > \
            above_factor * abs(misfits[-1] - misfits[-11])

    def end_stage(self, norm: float, level: float, spread: float, mu: float, stage: int,
                  growth: float, max_stages: int,
                  snapshot: Callable[[], dict[str, Any]]) -> StageEnd:
        """A stage with misfit ``norm`` ended (not ``stalled``): stop, a next stage, or
        the return to the accepted one. ``snapshot()`` is the solver's current state."""
        ok = norm <= level
        if self.direction is None:
            self.direction = "weaker" if not ok else "stronger"
        went_too_far = False
        if self.direction == "weaker":
            if ok:
                return StageEnd(Stop(True, StopReason.discrepancy))
            if self.accepted is not None and self.accepted["norm"] - norm < spread:
                # weaker TV fitted the data no closer than the noise's spread: the stage
                # before is the answer
                self.restore_pending, self.restore_reason = True, StopReason.plateau
                return StageEnd()
            # the stage to return to on a plateau (its linearisation is not kept: memory)
            self.accepted = {**snapshot(), "lin": None}
            mu_next = mu * growth
        elif not ok:
            went_too_far = True
        else:
            self.accepted = snapshot()
            mu_next = mu / growth
        if not went_too_far and stage + 1 < max_stages:
            return StageEnd(next_mu=mu_next)
        if self.direction == "stronger" and self.accepted is not None:
            if went_too_far:
                # The last stage fitted the data worse than the noise: back to the one before.
                self.restore_pending = True
                return StageEnd()
            return StageEnd(Stop(True, StopReason.discrepancy))
        return StageEnd(Stop(False, StopReason.max_iter))


__all__ = ["StageEnd", "StageSearch", "at_fixed_point", "fixed_weight_stop"]
