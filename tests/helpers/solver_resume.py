"""Exact-resume check shared by the solver tests: run once, snapshot ``state_dict()``
from a callback at several iterations, resume fresh solvers from those states."""
from __future__ import annotations

import copy
import dataclasses
import io
import math

import torch


def roundtrip(state):
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return torch.load(buffer, weights_only=True)


def same_scalars(a, b) -> bool:
    x = {k: v for k, v in a.scalars().items() if k != "wall_time"}
    y = {k: v for k, v in b.scalars().items() if k != "wall_time"}
    return x.keys() == y.keys() and all(
        x[k] == y[k] or (math.isnan(x[k]) and math.isnan(y[k])) for k in x)


def run_with_snapshots(solver, residual, theta0, at, extra=None):
    """Uninterrupted run; ``{k: state}`` for every ``k`` in ``at`` (and ``extra()``)."""
    snapshots = {}

    def callback(record):
        if record.iteration in at:
            snapshots[record.iteration] = (copy.deepcopy(solver.state_dict()),
                                           extra() if extra else None)

    return solver.solve(residual, theta0, [callback]), snapshots


def check_resume(full, resumed, k, counters=True):
    """``resumed`` continued the run of ``full`` after iteration ``k``, bit for bit.

    ``counters=False``: factorisation and solve counts are not compared. They can differ
    where the forward model's own solution cache served a point repeated from before the
    resume point (the resumed process starts with a cold cache); the iterates cannot."""
    after = [r for r in full.history if r.iteration > k]
    assert [r.iteration for r in resumed.history] == [r.iteration for r in after]
    for a, b in zip(after, resumed.history):
        assert torch.equal(a.theta, b.theta), a.iteration
        if not counters:
            a, b = (dataclasses.replace(r, factorizations=0, solves=0) for r in (a, b))
        assert same_scalars(a, b), (a.iteration, a.scalars(), b.scalars())
        assert a.wall_time <= b.wall_time + 10.0     # the clock continues (not from zero)
    assert torch.equal(resumed.theta, full.theta)
    assert (resumed.stop_reason, resumed.converged, resumed.iterations) == \
        (full.stop_reason, full.converged, full.iterations)
    if counters:
        assert (resumed.factorizations, resumed.solves) == (full.factorizations, full.solves)


def fresh(problem):
    """``problem.residual`` with a cold simulator cache, so that counters compare: a
    solution left in the cache by an earlier run would save a factorisation."""
    def residual():
        problem.equilibrium.clear_cache()
        return problem.residual()

    return residual
