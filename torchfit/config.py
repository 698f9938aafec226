"""Structured (validated) configs of the Hydra apps, registered with Hydra's ConfigStore.

The top levels reuse the run's options as fields, so that every default is written once:
:data:`FitConfig` is ``problem``, ``solver``, the settings of a run that are arguments of
:func:`~torchfit.run.fit` / :func:`~torchfit.run.fit_continued` (with their defaults),
then the fields of :class:`~torchfit.run.FitOptions`; :data:`VerifyConfig` is
``problem``, the fields of :class:`~torchfit.run.VerifyOptions` and ``solver``.
``tests/test_config.py`` fails where a setting gets a default of its own twice.

Schemas live in the ``schema/`` group so that the user-facing groups ``problem/`` and
``solver/`` list only real choices. The YAML files under ``conf/`` extend them; a misspelt
or mistyped override fails at composition time, before any run directory exists.
"""
from __future__ import annotations

import dataclasses
import inspect
import typing
from typing import Any, Callable, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from .problems import PROBLEMS
from .run import FitOptions, VerifyOptions, fit, fit_continued
from .solvers import SOLVERS


def _field(name: str, kind: Any, **default: Any) -> tuple[str, Any, dataclasses.Field]:
    return name, kind, dataclasses.field(**default)


def _argument(name: str, kind: Any, function: Callable[..., Any],
              parameter: str | None = None) -> tuple[str, Any, dataclasses.Field]:
    """A schema field whose default is that of ``function``'s keyword ``parameter``."""
    default = inspect.signature(function).parameters[parameter or name].default
    return _field(name, kind, default=default)


def _fields_of(options: type, names: list[str]) -> list[tuple[str, Any, dataclasses.Field]]:
    """``names`` of the dataclass ``options`` as fields of a schema: its types and defaults
    (its own, not restated)."""
    hints = typing.get_type_hints(options)
    fields = {f.name: f for f in dataclasses.fields(options)}
    out = []
    for name in names:
        f = fields[name]
        if f.default_factory is not dataclasses.MISSING:
            out.append(_field(name, hints[name], default_factory=f.default_factory))
        else:
            out.append(_field(name, hints[name], default=f.default))
    return out


#: Top level of ``experiments/fit.py``. ``resume``: continue from the last checkpoint in the
#: run directory. ``init``: start from an earlier run's fitted parameters (its directory or
#: ``params.pt``) instead of the problem's initial guess (the same parameterisation).
#: ``continuation``: fit the frames far from a fold first (no tetrahedron below
#: ``continuation_min_volume`` of its rest volume at the start; at most
#: ``continuation_first_max_iter`` iterations, null: 3 x ``solver.max_iter``), then all frames
#: from there: two runs in one, the first in ``<run>/unique_frames`` (bodies fitted to an
#: animation). ``true``, ``false`` or ``auto``: on for a synthetic target (the body's own
#: model) with frames near a fold at the start, off otherwise (``torchfit/run/continuation.py``).
FitConfig = dataclasses.make_dataclass("FitConfig", [
    _field("problem", Any, default=MISSING),
    _field("solver", Any, default=MISSING),
    _argument("resume", bool, fit),
    _argument("init", Optional[str], fit),
    _field("continuation", Any, default="auto"),       # true | false | auto
    _argument("continuation_min_volume", float, fit_continued, "min_volume"),
    _argument("continuation_first_max_iter", Optional[int], fit_continued, "first_max_iter"),
    *_fields_of(FitOptions, ["progress", "log_every", "threads", "snapshot_iterations",
                             "snapshot_every", "sheet_frame", "objective_metric",
                             "validation_patience"]),
])
FitConfig.__module__ = __name__

#: ``solver`` of the apps that do not fit: unused (a problem config may name one, e.g.
#: membrane2d's default solver)
_UNUSED_SOLVER = _field("solver", Any, default=None)

#: Top level of ``experiments/verify.py``; ``solver`` is unused.
VerifyConfig = dataclasses.make_dataclass("VerifyConfig", [
    _field("problem", Any, default=MISSING),
    *_fields_of(VerifyOptions, ["seed", "at", "perturbation", "taylor_tol", "dot_tol",
                                "fd_tol"]),
    _UNUSED_SOLVER,
    *_fields_of(VerifyOptions, ["threads"]),
])
VerifyConfig.__module__ = __name__


#: Top level of ``experiments/simulate.py``: ``run``, the fitted run (its directory or
#: ``params.pt``); ``problem``, the fit's problem group with the overrides that make the
#: animation to simulate (the rest of the fit's settings come from the run); ``solver`` is
#: unused (a problem config may name one).
SimulateConfig = dataclasses.make_dataclass("SimulateConfig", [
    _field("run", str, default=MISSING),
    _field("problem", Any, default=MISSING),
    _UNUSED_SOLVER,
    *_fields_of(FitOptions, ["progress", "threads"]),
])
SimulateConfig.__module__ = __name__


def register_configs() -> None:
    """Register every schema (idempotent)."""
    cs = ConfigStore.instance()
    cs.store(name="fit_schema", node=FitConfig)
    cs.store(name="verify_schema", node=VerifyConfig)
    cs.store(name="simulate_schema", node=SimulateConfig)
    for name, entry in PROBLEMS.items():
        cs.store(group="schema/problem", name=name, node=entry.config_class)
    for name, entry in SOLVERS.items():
        cs.store(group="schema/solver", name=name, node=entry.config_class)
