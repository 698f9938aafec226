"""The interface every linear-solve backend implements: a :class:`Backend` factorises, its
:class:`Factor` solves (``A x = b`` or ``A^T x = b``) as often as asked.

A backend counts each factorisation and each solve (:mod:`torchfit.linalg.counters`), and
raises :class:`~torchfit.linalg.errors.SingularMatrixError` for a matrix it cannot
factorise, so that callers can tell a singular system from a failed backend.
"""
from __future__ import annotations

from typing import Protocol

from torch import Tensor

from ..pattern import SparsePattern


class Factor(Protocol):
    """A matrix prepared for repeated solves."""

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        """Solve ``A x = rhs`` (or ``A^T x = rhs``); ``rhs`` is ``(n,)`` or ``(n, c)``."""


class Backend(Protocol):
    """A linear-solve backend: factorises a matrix of a pattern into a :class:`Factor`."""

    name: str

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> Factor:
        ...
