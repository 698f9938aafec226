"""Bounds on a rigged body's Young's modulus: which apply, their check, their ``theta``.

Settings (:class:`~.rigged_body_config.RiggedBodyConfig`): ``bounds`` (``null``: on for
``target=rig``, off for ``target=synthetic``), ``E_min``, ``E_max`` and
``E_bounds_relative`` (``true``: ``E_min`` and ``E_max`` are factors of ``E0``; ``false``:
moduli in the units of ``E0``). The defaults, ``[E0 / 100, 100 E0]`` for rig targets, and
why: ``docs/problems/bounds.md``.

The solvers enforce them (:mod:`torchfit.solvers.bounds`): the run hands them
:meth:`~.base.InverseProblem.theta_bounds`, the bounds on ``theta`` (``log E_min``,
``log E_max`` with ``transform=exp``; ``E_min``, ``E_max`` with ``identity``). Every
tetrahedron's modulus then lies in ``[E_min, E_max]`` too: the grid's trilinear weights and
the region/tetrahedron layouts map ``theta`` to convex combinations of the parameters.
"""
from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor

from .config import Transform, require_setting
from .rigged_body_config import RiggedBodyConfig, Target

#: a tetrahedron whose modulus is within this relative distance of a bound is on it
ON_BOUND_RTOL = 1e-6


def bounds_apply(cfg: RiggedBodyConfig) -> bool:
    """Whether the modulus is bounded (``bounds``; ``null``: rig targets only)."""
    return cfg.target == Target.rig if cfg.bounds is None else bool(cfg.bounds)


def modulus_bounds(cfg: RiggedBodyConfig) -> Optional[tuple[float, float]]:
    """``(E_min, E_max)`` as moduli, or ``None`` when the modulus is unbounded."""
    if not bounds_apply(cfg):
        return None
    scale = cfg.E0 if cfg.E_bounds_relative else 1.0
    return cfg.E_min * scale, cfg.E_max * scale


def check_bounds(cfg: RiggedBodyConfig) -> None:
    """Refuse bounds that are not a range of positive moduli holding ``E0`` (one line)."""
    if not bounds_apply(cfg):
        return
    kind = "factors of problem.E0" if cfg.E_bounds_relative else "moduli"
    require_setting(cfg.E_min > 0, cfg, "E_min", f"must be positive ({kind}; a Young's "
                    f"modulus is positive), e.g. 0.01; or set problem.bounds=false")
    require_setting(cfg.E_min < cfg.E_max, cfg, "E_min", f"must be below problem.E_max="
                    f"{cfg.E_max} ({kind})")
    low, high = modulus_bounds(cfg)
    require_setting(low <= cfg.E0 <= high, cfg, "E0", f"lies outside the bounds [{low:g}, "
                    f"{high:g}] (problem.E_min, problem.E_max"
                    f"{', absolute: problem.E_bounds_relative=false' if not cfg.E_bounds_relative else ''}); "
                    f"the start must lie inside them")


def theta_bounds(cfg: RiggedBodyConfig, n_params: int, like: Tensor
                 ) -> Optional[tuple[Tensor, Tensor]]:
    """``(lower, upper)`` on ``theta`` ``(n_params,)`` each, or ``None`` (unbounded)."""
    bounds = modulus_bounds(cfg)
    if bounds is None:
        return None
    low, high = bounds
    if cfg.transform == Transform.exp:
        low, high = math.log(low), math.log(high)
    return (torch.full((n_params,), low, dtype=like.dtype, device=like.device),
            torch.full((n_params,), high, dtype=like.dtype, device=like.device))


def fraction_on_bounds(values, bounds: Optional[tuple[float, float]]) -> dict[str, float]:
    """``{'at_lower': ..., 'at_upper': ...}``: fractions of ``values`` (a region's
    tetrahedra) on each bound (``{}`` without bounds)."""
    if bounds is None or len(values) == 0:
        return {}
    low, high = bounds
    return {"at_lower": float((values <= low * (1 + ON_BOUND_RTOL)).mean()),
            "at_upper": float((values >= high * (1 - ON_BOUND_RTOL)).mean())}
