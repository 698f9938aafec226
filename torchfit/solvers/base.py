"""What every solver shares: config validation, the outer loop, the stop rules, the run
clock, record emission and exact resume.

Contract of :class:`Solver`:

* ``Solver(config, D=..., groups=...)`` validates the config (:meth:`SolverConfig.validate`)
  and the operators the solver needs; a bad setting raises :class:`SolverConfigError`
  naming ``solver.<field>``.
* ``solve(residual, theta0, callbacks)`` runs one loop for every solver: initialise,
  emit record 0, then per outer iteration: stop rules -> :meth:`Solver.step` -> record
  -> emit. A callback returning ``True`` stops the run (``interrupted``).
* ``state_dict()``, called from a callback, returns everything needed to continue after
  the record just emitted (plain tensors, numbers, bools, strings, ``None``, lists and
  dicts: ``torch.load(weights_only=True)`` reads it). ``solve(..., state=state)`` on a
  fresh solver with the same config and operators re-linearises at the saved ``theta``
  (one extra simulation, not counted in the run's counters), does not emit that record
  again, numbers on from ``iteration + 1`` and continues the clock and counters. For a
  deterministic forward model the continuation is bit-identical to the uninterrupted
  run. ``max_iter`` is the budget of the whole run; ``SolveResult.history`` holds the
  records of this call, its ``iterations``, ``wall_time``, ``factorizations`` and
  ``solves`` are whole-run totals.
"""
from __future__ import annotations

import abc
import dataclasses
import enum
import math
import time
from typing import Any, ClassVar, Iterable, NamedTuple, Optional

from torch import Tensor

from ..errors import ConfigurationError, SimulationError
from ..linalg import SolveCounters, counting
from ..records import Callback, IterationRecord, SolveResult, StopReason
from ..settings import check_values


class SolverConfigError(ConfigurationError):
    """An invalid solver setting (or solver input); the message names it."""


class UnsimulatedStart(SolverConfigError):
    """The start cannot be simulated (a :class:`~torchfit.errors.SimulationError` there: a
    time step the integrator cannot take, Newton failing at the initial guess): bad input,
    refused in one line, where inside the fit the same error is a failed trial step."""


def require(condition: bool, message: str) -> None:
    """Raise :class:`SolverConfigError` with ``message`` unless ``condition``."""
    if not condition:
        raise SolverConfigError(message)


# -- configuration -------------------------------------------------------------------------
class Need(enum.Enum):
    """How a solver with given settings uses an operator of the parameterisation."""

    unused = "unused"            # not passed
    if_offered = "if_offered"    # passed where the parameterisation has one
    required = "required"        # a parameterisation without one cannot run the solver


@dataclasses.dataclass(frozen=True)
class Needs:
    """What a solver with given settings needs of the parameterisation
    (:meth:`SolverConfig.needs`; :func:`torchfit.solvers.build` acts on it).

    Attributes:
        difference_operator: the sparse difference operator ``D``.
        difference_groups: the row groups of ``D`` (isotropic TV), fetched where ``D``
            is required.
    """

    difference_operator: Need = Need.unused
    difference_groups: bool = False


@dataclasses.dataclass
class SolverConfig:
    """Settings every solver has. Subclasses add plain dataclass fields (Hydra schemas).

    :meth:`validate` checks every field generically (ints are ints, bools are bools,
    every number, also an optional one when set and inside lists, is finite), then
    ``max_iter >= 0``, then calls :meth:`check` for the solver's own rules.
    """

    name: str = "solver"
    max_iter: int = 50

    def validate(self) -> None:
        check_values(self, "solver", SolverConfigError)
        require(self.max_iter >= 0, f"solver.max_iter={self.max_iter}: must be >= 0")
        self.check()

    def check(self) -> None:
        """Solver-specific rules (called by :meth:`validate` after the generic checks)."""

    def needs(self) -> Needs:
        """What a solver with these settings needs of the parameterisation (default:
        nothing)."""
        return Needs()


# -- run clock and records -----------------------------------------------------------------
class RunClock:
    """Wall time and counters since the start of a run, continuing from saved offsets.

    ``spent`` is the counting scope of the solve (:func:`torchfit.linalg.counting`): what the
    solver, its simulations and its callbacks factorise and solve in it."""

    def __init__(self, spent: SolveCounters, wall_time: float = 0.0, factorizations: int = 0,
                 solves: int = 0) -> None:
        self.start = time.perf_counter()
        self.spent, self.base = spent, spent.snapshot()   # a resume's re-linearisation: before
        self.offsets = (float(wall_time), int(factorizations), int(solves))

    def elapsed(self) -> float:
        return self.offsets[0] + time.perf_counter() - self.start

    def counts(self) -> tuple[int, int]:
        spent = self.spent - self.base
        return self.offsets[1] + spent.factorizations, self.offsets[2] + spent.solves

    def state_dict(self) -> dict[str, Any]:
        factorizations, solves = self.counts()
        return {"wall_time": self.elapsed(), "factorizations": factorizations, "solves": solves}


def emit(callbacks: Iterable[Callback], record: IterationRecord) -> bool:
    """Send a record to every callback; ``True`` if one asked to stop."""
    stop = False
    for callback in callbacks:
        stop = bool(callback(record)) or stop
    return stop


class Stop(NamedTuple):
    """Why a run ends: ``converged`` and the :class:`~torchfit.records.StopReason`."""

    converged: bool
    reason: StopReason


def least_squares_stop(norm: float, previous_norm: Optional[float], gradient_norm: float,
                       gradient_norm0: float, noise_level: Optional[float], tau: float,
                       atol: float, gtol: float, rtol: float) -> Optional[Stop]:
    """The outer stop rules of the least-squares solvers, in order: the discrepancy
    principle ``||r|| <= tau delta`` (noise level known); ``||r|| <= atol``,
    ``||J^T r|| <= gtol ||J^T r_0||`` or a zero gradient; without a noise level, a
    relative decrease ``||r_{k-1}|| - ||r_k|| <= rtol ||r_{k-1}||``."""
    if noise_level is not None and norm <= tau * noise_level:
        return Stop(True, StopReason.discrepancy)
    if norm <= atol or gradient_norm <= gtol * gradient_norm0 or gradient_norm == 0.0:
        return Stop(True, StopReason.tolerance)
    if previous_norm is not None and noise_level is None \
            and previous_norm - norm <= rtol * previous_norm:
        return Stop(True, StopReason.tolerance)
    return None


# -- the solver ----------------------------------------------------------------------------
class Solver(abc.ABC):
    """Base of every solver: one outer loop, stop rules, records and exact resume.

    Subclasses set :attr:`config_class` and implement :meth:`start` (initialise at
    ``theta0``, return record 0), :meth:`step` (one outer iteration: a record or a
    :class:`Stop`), :meth:`stop_rule` (checked before every step), and
    :meth:`_get_state` / :meth:`_set_state` / :meth:`resume` (their carried state).
    """

    config_class: ClassVar[type[SolverConfig]]
    #: keeps theta inside bounds given by :meth:`set_bounds` (see :mod:`.bounds`)
    supports_bounds: ClassVar[bool] = False

    def __init__(self, config: SolverConfig | None = None, *, D: Tensor | None = None,
                 groups: Tensor | None = None) -> None:
        config = config if config is not None else self.config_class()
        if not isinstance(config, self.config_class):
            raise TypeError(f"{type(self).__name__} takes a {self.config_class.__name__}, got "
                            f"{type(config).__name__}")
        config.validate()
        self.config = config
        self.D = D
        self.groups = groups
        self.residual: Any = None
        self.iteration = 0
        self.clock: RunClock | None = None
        self._started = False
        self.bounds: Any = None            # a .bounds.ThetaBounds after set_bounds

    def set_bounds(self, lower: Tensor, upper: Tensor) -> None:
        """Keep every iterate within ``lower <= theta <= upper`` (:mod:`.bounds`; solvers
        with ``supports_bounds`` override this). A solver that cannot refuses
        (:class:`SolverConfigError`, one line), as do bounds that are not a box."""
        raise SolverConfigError(
            f"solver={self.config.name} cannot keep the parameters within bounds; use "
            f"solver=levenberg_marquardt or solver=gauss_newton, or turn the bounds off")

    # -- subclass hooks --------------------------------------------------------------------
    @abc.abstractmethod
    def start(self, theta0: Tensor) -> IterationRecord:
        """Initialise at ``theta0`` (after the clock started); return record 0."""

    @abc.abstractmethod
    def step(self) -> IterationRecord | Stop:
        """One outer iteration (``self.iteration`` is already its number)."""

    def stop_rule(self) -> Stop | None:
        """Checked before every step (and once more when the budget is spent)."""
        return None

    def budget_exhausted(self) -> bool:
        return self.iteration >= self.config.max_iter

    @abc.abstractmethod
    def _get_state(self) -> dict[str, Any]:
        """The solver's carried state (see :meth:`state_dict`)."""

    @abc.abstractmethod
    def _set_state(self, state: dict[str, Any]) -> None:
        """Inverse of :meth:`_get_state` (no simulation)."""

    @abc.abstractmethod
    def resume(self) -> None:
        """Rebuild what is not saved (the linearisation at ``theta``: one simulation)."""

    # -- the loop --------------------------------------------------------------------------
    def record(self, theta: Tensor, objective: float, misfit: float, step_norm: float = 0.0,
               cg_iterations: int = 0, damping: float = math.nan, accepted: bool = True,
               **extra: float) -> IterationRecord:
        """A record of the current iteration, clock and counters filled in."""
        assert self.clock is not None
        factorizations, solves = self.clock.counts()
        return IterationRecord(self.iteration, theta, objective, misfit, step_norm,
                               cg_iterations, damping, accepted, self.clock.elapsed(),
                               factorizations, solves, dict(extra))

    def solve(self, residual: Any, theta0: Tensor, callbacks: Iterable[Callback] = (), *,
              state: dict[str, Any] | None = None) -> SolveResult:
        """Run from ``theta0``, or continue a run from ``state`` (a :meth:`state_dict`).

        With ``state`` the solver re-linearises at the saved ``theta`` (one simulation,
        not counted in the records' counters), emits nothing for the saved iteration and
        continues with ``iteration + 1``; ``theta0`` is then ignored.
        """
        with counting() as spent:
            return self._solve(residual, theta0, list(callbacks), state, spent)

    def _solve(self, residual: Any, theta0: Tensor, callbacks: list[Callback],
               state: dict[str, Any] | None, spent: SolveCounters) -> SolveResult:
        self.residual = residual
        history: list[IterationRecord] = []
        if self.bounds is not None:
            self.bounds = self.bounds.to(theta0 if state is None else state["theta"])
            self.bounds.check_start(theta0 if state is None else state["theta"])
        if state is None:
            self.iteration = 0
            self.clock = RunClock(spent)
            self._started = True
            try:
                record = self.start(theta0)
            except SimulationError as error:
                raise UnsimulatedStart(f"the fit's start cannot be simulated: "
                                       f"{' '.join(str(error).split())}") from error
            history.append(record)
            if emit(callbacks, record):
                return self._finish(Stop(False, StopReason.interrupted), history)
        else:
            self.load_state_dict(state)
            self.resume()
            self.clock = RunClock(spent, state["wall_time"], state["factorizations"],
                                  state["solves"])
            self._started = True
        while True:
            stop = self.stop_rule()
            if stop is None and self.budget_exhausted():
                stop = Stop(False, StopReason.max_iter)
            if stop is None:
                self.iteration += 1
                outcome = self.step()
                if isinstance(outcome, Stop):
                    self.iteration -= 1          # no record: the run ends where it was
                    stop = outcome
                else:
                    history.append(outcome)
                    if emit(callbacks, outcome):
                        stop = Stop(False, StopReason.interrupted)
            if stop is not None:
                return self._finish(stop, history)

    def _finish(self, stop: Stop, history: list[IterationRecord]) -> SolveResult:
        assert self.clock is not None
        factorizations, solves = self.clock.counts()
        return SolveResult(self.theta, stop.converged, stop.reason, self.iteration, history,
                           self.clock.elapsed(), factorizations, solves)

    @property
    @abc.abstractmethod
    def theta(self) -> Tensor:
        """The current parameters."""

    # -- state -----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue after the last emitted record.

        ``iteration``, ``theta``, the clock (``wall_time``, ``factorizations``,
        ``solves``) and the solver's carried state; plain values only
        (``torch.load(weights_only=True)`` reads it)."""
        if not self._started or self.clock is None:
            raise RuntimeError("state_dict() before solve(): nothing to save")
        state = {"solver": self.config.name, "iteration": self.iteration,
                 "theta": self.theta.detach().clone()}
        state.update(self.clock.state_dict())
        state.update(self._get_state())
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take over a :meth:`state_dict` (the next :meth:`solve` needs ``state=``)."""
        missing = [k for k in ("iteration", "theta", "wall_time", "factorizations", "solves")
                   if k not in state]
        if missing:
            raise ValueError(f"solver state lacks {missing}")
        self.iteration = int(state["iteration"])
        self._set_state(state)


def clone(value: Any) -> Any:
    """A detached copy of a tensor (or ``None``/number) for a state dict."""
    return value.detach().clone() if isinstance(value, Tensor) else value


__all__ = ["Need", "Needs", "RunClock", "Solver", "SolverConfig", "SolverConfigError", "Stop",
           "emit", "least_squares_stop", "require"]
