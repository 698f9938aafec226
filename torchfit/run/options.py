"""The settings of one run: how a fit reports itself, and where ``verify`` checks.

:class:`FitOptions` and :class:`VerifyOptions` hold every top-level default of the two
verbs once; the Hydra schemas (:mod:`torchfit.config`) reuse their fields, ``verify``'s
keyword settings are :class:`VerifyOptions` fields. Every check raises
:class:`FitConfigError` with one line naming the setting.
"""
from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any

from ..errors import ConfigurationError
from ..problems import FramedProblem, InverseProblem
from ..reporting import jsonable
from .validation import RESULT_KEYS as VALIDATION_RESULT_KEYS

#: Counters a result reports beside the metrics; ``objective_metric`` may name them too.
COUNT_KEYS = ("iterations", "wall_s", "factorizations", "solves")


class FitConfigError(ConfigurationError):
    """A setting of the run itself (not of the problem or solver) is invalid."""


def _need(ok: bool, message: str) -> None:
    if not ok:
        raise FitConfigError(message)


#: more threads than this is a slip of the keyboard (torch takes a C int)
MAX_THREADS = 4096


def check_threads(value: Any) -> None:
    """Refuse ``threads`` that is not an integer from 0 (torch's default) to
    :data:`MAX_THREADS` (:class:`FitConfigError`, one line)."""
    _need(_is_int(value) and 0 <= value <= MAX_THREADS,
          f"threads={value!r} must be an integer from 0 (torch's default) to {MAX_THREADS}")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


@dataclasses.dataclass
class ProcessOptions:
    """What a verb sets of its process.

    Attributes:
        threads: torch and BLAS CPU threads of this process (0: leave as they are); 1 in
            joblib sweeps.
    """

    threads: int = 0


@dataclasses.dataclass
class FitOptions(ProcessOptions):
    """How a run reports itself (none of it changes the fit but ``validation_patience``,
    which may end it early); ``threads``: :class:`ProcessOptions`.

    Attributes:
        progress: one line per outer iteration through the ``torchfit.progress`` logger.
        log_every: TensorBoard scalars every ``n`` iterations (the last one always).
        snapshot_iterations: 2-D fields: the field and error images after these
            iterations (``snapshots.png``, the seed's figure) and in TensorBoard.
        snapshot_every: also every ``n`` iterations in TensorBoard (0: only those).
        sheet_frame: frame whose deformed mesh is drawn (``None``: the problem's choice).
        objective_metric: the key of ``result.json`` that :attr:`FitResult.objective`
            returns, i.e. what a sweeper such as Optuna minimises (a metric of
            docs/problems.md, or ``iterations``, ``wall_s``, ``factorizations``, ``solves``).
        fold_hint: a 3-D body's warning about folded frames at the end suggests
            ``continuation=true`` (off in the stages of one, which report themselves).
        validation_patience: with frames held out of the fit (a body's
            ``problem.validation_frames`` or ``validation_every``), stop the fit after this
            many accepted iterations without a lower validation error (stop reason
            ``validation``; 0: never stop early). The chosen iteration (lowest validation
            error) is reported either way (:mod:`.validation`).
    """

    progress: bool = True
    log_every: int = 1
    snapshot_iterations: list[int] = dataclasses.field(default_factory=lambda: [1, 5, 10, 40])
    snapshot_every: int = 10
    sheet_frame: int | None = None
    objective_metric: str = "misfit"
    fold_hint: bool = True
    validation_patience: int = 5

    def check(self, problem: InverseProblem, validated: bool = False) -> None:
        """Raise :class:`FitConfigError` naming the first invalid option (``validated``: the
        run has a validation problem, whose keys ``objective_metric`` may name)."""
        _need(isinstance(self.progress, bool), f"progress={self.progress!r} must be true or false")
        check_threads(self.threads)
        for key, low in (("log_every", 1), ("snapshot_every", 0), ("validation_patience", 0)):
            value = getattr(self, key)
            _need(_is_int(value) and value >= low, f"{key}={value!r} must be an integer >= {low}")
        _need(all(isinstance(i, int) and i >= 0 for i in self.snapshot_iterations),
              f"snapshot_iterations={list(self.snapshot_iterations)} must be integers >= 0")
        allowed = list(problem.metric_names()) + list(COUNT_KEYS) + (
            list(VALIDATION_RESULT_KEYS) if validated else [])
        _need(self.objective_metric in allowed,
              f"objective_metric={self.objective_metric} is not reported by {problem.name}; "
              f"choose one of {allowed}")
        if self.sheet_frame is not None:
            n = problem.n_frames if isinstance(problem, FramedProblem) else 0
            _need(isinstance(self.sheet_frame, int) and n > 0 and -n <= self.sheet_frame < n,
                  f"sheet_frame={self.sheet_frame!r} is not a frame of {problem.name}"
                  + (f" (0..{n - 1})" if n else " (it has no frames to draw)"))


class VerifyPoint(str, enum.Enum):
    """Where ``verify`` checks the derivatives (before a random offset)."""

    initial = "initial"
    truth = "truth"


@dataclasses.dataclass
class VerifyOptions(ProcessOptions):
    """Where and how strictly ``verify`` checks a problem's Jacobian; ``threads``:
    :class:`ProcessOptions`.

    Attributes:
        seed: of the random point offset and the directions.
        at: ``initial`` (the problem's initial guess) or ``truth`` (its true parameters).
        perturbation: relative size of the seeded random offset of ``theta`` from there.
        taylor_tol: ``|rate - 2|`` allowed.
        dot_tol: relative ``|<Jv, w> - <v, J^T w>|`` allowed; ``None``: 1e-10 where
            ``J^T w`` is the exact transpose of ``J v``, ``1000 rtol`` for torchdiffeq's
            continuous adjoint (:func:`torchfit.verification.default_dot_tol`).
        fd_tol: relative ``|Jv - central FD|`` allowed; ``None``: ``max(1e-6, 100 a^(2/3))``
            with ``a`` the simulation's accuracy (Newton's rtol).
    """

    seed: int = 0
    at: VerifyPoint = VerifyPoint.initial
    perturbation: float = 0.1
    taylor_tol: float = 0.05
    dot_tol: float | None = None
    fd_tol: float | None = None

    def check(self) -> None:
        """Raise :class:`FitConfigError` naming the first invalid setting."""
        for name in ("taylor_tol", "dot_tol", "fd_tol"):
            value = getattr(self, name)
            if name in ("fd_tol", "dot_tol") and value is None:
                continue
            _need(isinstance(value, (int, float)) and math.isfinite(value) and value > 0,
                  f"{name}={value!r} must be a finite number > 0")
        _need(self.at in [p.value for p in VerifyPoint],
              f"at={self.at!r} is not a point to verify at; choose one of "
              f"{[p.value for p in VerifyPoint]}")
        _need(isinstance(self.perturbation, (int, float)) and math.isfinite(self.perturbation)
              and self.perturbation >= 0,
              f"perturbation={self.perturbation!r} must be a finite number >= 0")
        check_threads(self.threads)


def plain_settings(config: Any) -> dict[str, Any]:
    """Plain JSON values of a config dataclass or mapping (Enums as their values)."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    return jsonable(dict(config))
