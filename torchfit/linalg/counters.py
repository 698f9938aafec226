"""Counters of sparse factorisations and solves, scoped to the block that asks for them.

Every factorisation a backend makes and every solve it performs with an existing factor is
counted, so that tests, benchmarks and a run's records can assert the cost model (one
factorisation per distinct parameter vector, about ``2m + 1`` solves per Gauss-Newton step
with ``m`` CG iterations; ``docs/architecture.md``) instead of trusting it.

There is no process-wide total. A block that wants counts opens a scope,
``with counting() as spent: ...``, and ``spent`` receives what the block does (and what
blocks nested in it do). A solver's run opens one for its whole solve, a test one for the
call it measures. ``counting(isolated=True)`` keeps a block's work out of the scopes around
it (a validation simulation is not the solver's work). Scopes follow the Python context
(:mod:`contextvars`), so each thread has its own; a computation that continues on another
thread (autograd's device threads run a CUDA backward) re-enters the scopes of the thread it
started on with :func:`within`.

A *solve* is one application of a factor to a block of right-hand sides (all frames or
components that share the factor are one solve); ``rhs_columns`` counts the columns. An
*analysis* is the ordering and symbolic factorisation of a sparsity pattern, counted by the
backends that keep it apart from the numeric factorisations (``pardiso``, ``ldl``,
``cudss``: one per pattern, whatever the number of frames and Newton steps); SuperLU and the
iterative backends analyse inside each factorisation or not at all and count none.
"""
from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from typing import Iterator

from torch import Tensor


@dataclasses.dataclass
class SolveCounters:
    """Factorisations, solves, right-hand-side columns and pattern analyses counted in one
    scope."""

    factorizations: int = 0
    solves: int = 0
    rhs_columns: int = 0
    analyses: int = 0

    def snapshot(self) -> "SolveCounters":
        return dataclasses.replace(self)

    def __sub__(self, other: "SolveCounters") -> "SolveCounters":
        return SolveCounters(self.factorizations - other.factorizations,
                             self.solves - other.solves, self.rhs_columns - other.rhs_columns,
                             self.analyses - other.analyses)

    def add(self, other: "SolveCounters") -> None:
        self.factorizations += other.factorizations
        self.solves += other.solves
        self.rhs_columns += other.rhs_columns
        self.analyses += other.analyses

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


#: the scopes the current context counts into, innermost last
_SCOPES: contextvars.ContextVar[tuple[SolveCounters, ...]] = contextvars.ContextVar(
    "torchfit_solve_counters", default=())


def credit(counts: SolveCounters) -> None:
    """Add ``counts`` to every open scope (work done elsewhere: another rank's, or a
    correction such as a solve handed on to a fallback backend)."""
    for scope in _SCOPES.get():
        scope.add(counts)


def count_factorization() -> None:
    """One numeric factorisation (a backend calls this when it makes one)."""
    credit(SolveCounters(factorizations=1))


def count_analysis() -> None:
    """One analysis (ordering and symbolic factorisation) of a sparsity pattern."""
    credit(SolveCounters(analyses=1))


def count_solve(rhs: Tensor | int) -> None:
    """One solve with ``rhs`` (``(n,)`` or ``(n, k)``, or the number of columns)."""
    columns = rhs if isinstance(rhs, int) else (1 if rhs.dim() == 1 else int(rhs.shape[1]))
    credit(SolveCounters(solves=1, rhs_columns=columns))


@contextlib.contextmanager
def counting(isolated: bool = False) -> Iterator[SolveCounters]:
    """``with counting() as c: ...; c.factorizations`` counts what the block does; with
    ``isolated``, the scopes around the block do not see it."""
    counts = SolveCounters()
    token = _SCOPES.set((counts,) if isolated else _SCOPES.get() + (counts,))
    try:
        yield counts
    finally:
        _SCOPES.reset(token)


def active_scopes() -> tuple[SolveCounters, ...]:
    """The scopes this context counts into (for :func:`within` on another thread)."""
    return _SCOPES.get()


@contextlib.contextmanager
def within(scopes: tuple[SolveCounters, ...]) -> Iterator[None]:
    """Count into ``scopes`` (taken with :func:`active_scopes` where the work started)."""
    token = _SCOPES.set(scopes)
    try:
        yield
    finally:
        _SCOPES.reset(token)
