"""What Gauss-Newton and Levenberg-Marquardt share beyond :class:`~.base.Solver`: the
linearisation they carry (``lin``, whose ``theta`` is the current point) and the
difference operator their ``preconditioner=difference`` needs."""
from __future__ import annotations

from typing import Optional

from torch import Tensor

from ..residual import Linearization
from .base import Solver, SolverConfig, SolverConfigError
from .total_variation import check_difference_operator


def require_difference_operator(D: Optional[Tensor]) -> None:
    """The error of ``preconditioner=difference`` without ``D`` (and a check of ``D``)."""
    if D is None:
        raise SolverConfigError(
            "solver.preconditioner=difference needs the difference operator D of the "
            "parameterisation (pass D=parameterization.difference_operator()), or set "
            "solver.preconditioner=none")
    n = D.shape[1] if isinstance(D, Tensor) and D.dim() == 2 else 0
    check_difference_operator(D, n)


class LeastSquaresSolver(Solver):
    """A solver of ``min 0.5 ||r(theta)||^2`` that carries its current linearisation.

    Its config has a ``preconditioner`` setting; ``difference`` requires ``D``.
    """

    def __init__(self, config: SolverConfig | None = None, *, D: Tensor | None = None,
                 groups: Tensor | None = None) -> None:
        super().__init__(config, D=D, groups=groups)
        if getattr(self.config, "preconditioner", "none") == "difference":
            require_difference_operator(D)
        self.lin: Linearization | None = None

    @property
    def theta(self) -> Tensor:
        assert self.lin is not None
        return self.lin.theta
