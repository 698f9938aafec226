"""Bounds on a rigged body's Young's modulus: which apply, their check, their ``theta``.

Settings (:class:`~.config.RiggedBodyConfig`): ``bounds`` (``null``: on for
``target=rig``, off for ``target=synthetic``), ``E_min``, ``E_max`` and
``E_bounds_relative`` (``true``: ``E_min`` and ``E_max`` are factors of ``E0``; ``false``:
moduli in the units of ``E0``). The defaults, ``[E0 / 100, 100 E0]`` for rig targets, and
why: ``docs/notes/bounds.md``.

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

from .report import ON_BOUND_RTOL, region_summary
from ..config import Transform, require_setting
from .config import RiggedBodyConfig, Target



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


def damping_theta_bounds(cfg: RiggedBodyConfig, band, n_scalars: int, like: Tensor
                         ) -> tuple[Tensor, Tensor]:
    """``(lower, upper)`` on the scalars' ``theta`` in time ``(n_scalars,)`` each: ``alpha
    <= alpha_max``, ``beta <= beta_max`` of the damping's band (``band``: a
    :class:`~torchfit.problems.damping.DampingBand`, or ``None``: unbounded above), in
    ``log`` with ``transform=exp`` (below: ``-inf``) or as they are (below: 0); a density
    scale unbounded. Where ``bounds_apply`` (rig targets by default) with the modulus'."""
    exp = cfg.transform == Transform.exp
    low = -math.inf if exp else 0.0
    highs = [math.inf] * n_scalars
    if band is not None:
        for i, bound in enumerate((band.alpha_max, band.beta_max)):
            highs[i] = (math.log(bound) if exp else bound) if math.isfinite(bound) else math.inf
    return (torch.full((n_scalars,), low, dtype=like.dtype, device=like.device),
            torch.tensor(highs, dtype=like.dtype, device=like.device))


def add_parameter_fractions(summary: dict[str, dict[str, float]], basis: Optional[Tensor],
                            field: Tensor, labels, names: list[str],
                            bounds: Optional[tuple[float, float]]) -> None:
    """Add to each region of ``summary`` (:func:`~.report.region_summary`) the
    parameters that act on it (a non-zero basis weight in one of its tetrahedra:
    ``params``) and the fractions of them on each bound (``params_at_lower``,
    ``params_at_upper``). A grid node on a bound rarely puts a tetrahedron on it (the
    trilinear weights mix it with its neighbours), so this is where a bound shows.

    The parameters' moduli are the least-squares pre-image of ``field`` under ``basis``
    (exact: the basis has full column rank on the parameters that act on some tetrahedron);
    ``basis=None`` (one parameter per tetrahedron): the field itself."""
    if bounds is None:
        return
    field = field.detach().to(torch.float64).cpu()
    n_cells = field.numel()
    labels_t = torch.zeros(n_cells, dtype=torch.long) if labels is None \
        else torch.as_tensor(labels, dtype=torch.long)
    if basis is None:
        dense = None
        values = field
    else:
        dense = (basis.to_dense() if basis.layout != torch.strided else basis).to(field).cpu()
        acting = (dense != 0).any(dim=0)
        values = torch.zeros(dense.shape[1], dtype=field.dtype)
        values[acting] = torch.linalg.lstsq(dense[:, acting], field[:, None]).solution[:, 0]
    low, high = bounds
    on_lower = values <= low * (1 + ON_BOUND_RTOL)
    on_upper = values >= high * (1 - ON_BOUND_RTOL)
    for r, name in enumerate(names or ["body"]):
        if name not in summary:
            continue
        cells = labels_t == r
        region_params = cells if dense is None else (dense[cells] != 0).any(dim=0)
        count = int(region_params.sum())
        summary[name].update({
            "params": count,
            "params_at_lower": float(on_lower[region_params].sum()) / max(count, 1),
            "params_at_upper": float(on_upper[region_params].sum()) / max(count, 1)})


def region_report(field: Tensor, volumes, labels, names: list[str], basis: Optional[Tensor],
                  bounds: Optional[tuple[float, float]]) -> dict[str, dict[str, float]]:
    """:func:`~.report.region_summary` of ``field`` with, under ``bounds``, the
    tetrahedra and the parameters on each bound (:func:`add_parameter_fractions`)."""
    out = region_summary(field.detach().cpu().numpy(), volumes, labels, names, bounds)
    add_parameter_fractions(out, basis, field, labels, names, bounds)
    return out


#: the fraction of the parameters on a bound above which a fit warns
ON_BOUND_WARN_FRACTION = 0.1


def bounds_warning(cfg: RiggedBodyConfig, n_params: int, at_lower: int,
                   at_upper: int) -> Optional[str]:
    """One line where more than a tenth of the ``n_params`` parameters ended on a bound
    (``at_lower``, ``at_upper`` of them): which bound, and the setting that moves it; else
    ``None``."""
    bounds = modulus_bounds(cfg)
    if bounds is None or at_lower + at_upper <= ON_BOUND_WARN_FRACTION * n_params:
        return None
    unit = " x E0" if cfg.E_bounds_relative else ""
    parts = []
    if at_lower:
        parts.append(f"{at_lower} on the lower bound {bounds[0]:g} (problem.E_min="
                     f"{cfg.E_min:g}{unit}; widen with e.g. problem.E_min={cfg.E_min / 10:g})")
    if at_upper:
        parts.append(f"{at_upper} on the upper bound {bounds[1]:g} (problem.E_max="
                     f"{cfg.E_max:g}{unit}; widen with e.g. problem.E_max={cfg.E_max * 10:g})")
    return (f"{at_lower + at_upper} of {n_params} parameters ended on a bound of the modulus: "
            f"{'; '.join(parts)}; the data push the material past that range there "
            "(problem.bounds=false lifts the bounds)")
