"""``problem.init_field``: a body's fit starts from a material layer (a painted one, a run's).

The layer (:mod:`torchfit.mesh.formats.usd.material`) gives a modulus per tetrahedron of
the body (:func:`~torchfit.mesh.formats.usd.material.layer_cell_values`; a layer of another
body is refused in one line). It is projected on the parameters by least squares in the
field: ``v = argmin ||B v - E||`` over the basis ``B`` of the parameterisation (exact for
``parameters=tet``, the region means for ``region``, the grid's pre-image for ``grid``),
values below ``1e-3`` of the field's mean raised to it (a least-squares pre-image may
undershoot), values outside the modulus bounds (``problem.E_min``, ``E_max``: a fitted field
that sits on a bound projects a little past it) clipped into them and said in one warning,
then ``theta = log v`` (``exp`` transform) or ``v``. One log line says which layer was read. Iteration 0's field is
``B v``: the layer itself for ``tet``, its projection otherwise. Scalars the parameters
carry beside the field (the body in time's damping) start at their own settings
(``alpha0``, ``beta0``).

Units: a quasistatic body is scale-free and takes the layer's values as a starting shape,
whatever their unit. The body in time is not (inertia fixes the scale; its moduli are
pascals), so it reads the unit the layer states (:attr:`ModulusLayer.unit`): ``Pa`` as
written; ``relative to problem.E0`` (what a scale-free fit writes) times the problem's
``E0`` in pascals; a layer that states none (a painted one) in the units of the problem's
modulus settings (``problem.E0_unit``: factors of ``problem.E_reference``, or pascals).
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...mesh import MeshError
from ...mesh.formats.usd import ModulusLayer, layer_cell_values, read_modulus_layer
from ..config import setting_error
from .bounds import modulus_bounds

log = logging.getLogger("torchfit.problems")

#: a least-squares value below this fraction of the layer's mean is raised to it
FLOOR = 1e-3


def layer_to_pascals(layer: ModulusLayer, cfg: Any, unitless: float) -> float:
    """The factor that makes ``layer``'s values pascals for a body whose ``cfg.E0`` is in
    pascals; ``unitless``: the factor for a layer that states no unit (module docstring)."""
    if layer.unit == "Pa":
        return 1.0
    if layer.relative:
        return float(cfg.E0)
    if not layer.unit:
        return float(unitless)
    raise setting_error("init_field", cfg.init_field, f"{layer.prim}: primvars:youngsModulus "
                        f"states the unit {layer.unit!r}, which torchfit does not read; write "
                        "it in Pa (customData torchfit:units = 'Pa') or leave the unit out "
                        "(then it is read in the units of problem.E0)")


def initial_field_theta(problem: Any, cfg: Any, unitless: float | None = None) -> Tensor:
    """``theta0`` of ``cfg.init_field`` for ``problem`` (a built :class:`RiggedBody`).
    ``unitless``: ``None`` for a scale-free body (the values as written); else the problem's
    moduli are pascals and a layer without a unit is multiplied by it (:func:`layer_to_pascals`)."""
    animation = problem.animation
    try:
        layer = read_modulus_layer(cfg.init_field)
        field = layer_cell_values(
            layer, str(cfg.init_field), file_rest=animation.file_points(animation.rest_vertices),
            file_vertices=animation.file_vertices, rest=animation.rest_vertices,
            points=np.asarray(problem.mesh.points), cells=np.asarray(problem.mesh.cells))
    except MeshError as err:
        raise setting_error("init_field", cfg.init_field, str(err)) from err
    if unitless is not None:
        field = field * layer_to_pascals(layer, cfg, unitless)
    log.info("start: problem.init_field=%s: %s, %d values per %s, %.3g to %.3g %s",
             cfg.init_field, layer.prim, len(layer.values),
             "tetrahedron" if layer.kind == "tet" else "vertex", float(np.min(layer.values)),
             float(np.max(layer.values)), layer.unit or "(no unit stated)")
    whole = problem.parameterization
    # the field's own parameterisation where scalars ride beside it (FieldAndScalars)
    parameterization = getattr(whole, "field_parameterization", whole)
    target = torch.as_tensor(field, dtype=problem.dtype, device=problem.device)
    basis = parameterization.basis
    if basis is None:
        values = target
    else:
        dense = (basis.to_dense() if basis.layout != torch.strided else basis).to(target)
        values = torch.linalg.lstsq(dense, target[:, None]).solution[:, 0]
    values = torch.clamp(values, min=FLOOR * float(target.mean()))
    # quasistatic only: there the layer's values and the bounds share the unit of problem.E0;
    # in time the values are pascals (the bounds' unit conversion is the body in time's)
    bounds = modulus_bounds(cfg) if unitless is None else None
    if bounds is not None:
        outside = (values < bounds[0]) | (values > bounds[1])
        if bool(outside.any()):
            factor = float(torch.maximum(bounds[0] / values, values / bounds[1]).max())
            log.warning("problem.init_field: %d of %d start values lie outside the modulus "
                        "bounds [%.4g, %.4g] (by up to %.3gx: the layer's field projected on "
                        "the parameters); clipped into them", int(outside.sum()),
                        values.numel(), bounds[0], bounds[1], factor)
            values = torch.clamp(values, bounds[0], bounds[1])
    theta_field = torch.log(values) if parameterization.transform == "exp" else values
    if parameterization is whole:
        return theta_field
    theta = whole.constant(1.0, problem.dtype, problem.device)    # the scalars' own starts
    theta[:parameterization.n_params] = theta_field
    return theta
