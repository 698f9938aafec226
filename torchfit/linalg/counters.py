"""Counters of sparse factorisations and solves.

Every factorisation a backend makes and every solve it performs with an existing
factor is counted here, so that tests and benchmarks can assert the cost model of
DESIGN.md (one factorisation per distinct parameter vector, about ``2m + 1`` solves
per Gauss-Newton step with ``m`` CG iterations) instead of trusting it.

A *solve* is one application of a factor to a block of right-hand sides (all frames
or components that share the factor are one solve).
"""
from __future__ import annotations

import contextlib
import dataclasses
from typing import Iterator


@dataclasses.dataclass
class SolveCounters:
    """Running totals; read them directly or take differences with :func:`counting`."""

    factorizations: int = 0
    solves: int = 0
    rhs_columns: int = 0

    def reset(self) -> None:
        self.factorizations = 0
        self.solves = 0
        self.rhs_columns = 0

    def snapshot(self) -> "SolveCounters":
        return dataclasses.replace(self)

    def __sub__(self, other: "SolveCounters") -> "SolveCounters":
        return SolveCounters(
            self.factorizations - other.factorizations,
            self.solves - other.solves,
            self.rhs_columns - other.rhs_columns,
        )

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


COUNTERS = SolveCounters()


class _Delta:
    """Live view of the counters since a start snapshot."""

    def __init__(self) -> None:
        self._start = COUNTERS.snapshot()

    @property
    def factorizations(self) -> int:
        return COUNTERS.factorizations - self._start.factorizations

    @property
    def solves(self) -> int:
        return COUNTERS.solves - self._start.solves

    @property
    def rhs_columns(self) -> int:
        return COUNTERS.rhs_columns - self._start.rhs_columns

    def as_dict(self) -> dict[str, int]:
        return {"factorizations": self.factorizations, "solves": self.solves,
                "rhs_columns": self.rhs_columns}


@contextlib.contextmanager
def counting() -> Iterator[_Delta]:
    """``with counting() as c: ...; c.factorizations`` counts only what the block did."""
    yield _Delta()


def reset_counters() -> None:
    COUNTERS.reset()
