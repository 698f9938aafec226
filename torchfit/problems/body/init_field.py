"""``problem.init_field``: a body's fit starts from a material layer (a painted one, a run's).

The layer (:mod:`torchfit.mesh.formats.usd.material`) gives a modulus per tetrahedron of
the body (:func:`~torchfit.mesh.formats.usd.material.layer_cell_values`; a layer of another
body is refused in one line). It is projected on the parameters by least squares in the
field: ``v = argmin ||B v - E||`` over the basis ``B`` of the parameterisation (exact for
``parameters=tet``, the region means for ``region``, the grid's pre-image for ``grid``),
values below ``1e-3`` of the field's mean raised to it (a least-squares pre-image may
undershoot), then ``theta = log v`` (``exp`` transform) or ``v``. Iteration 0's field is
``B v``: the layer itself for ``tet``, its projection otherwise.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...mesh import MeshError
from ...mesh.formats.usd.material import layer_cell_values, read_modulus_layer
from ..config import setting_error

#: a least-squares value below this fraction of the layer's mean is raised to it
FLOOR = 1e-3


def initial_field_theta(problem: Any, cfg: Any) -> Tensor:
    """``theta0`` of ``cfg.init_field`` for ``problem`` (a built :class:`RiggedBody`)."""
    animation = problem.animation
    try:
        layer = read_modulus_layer(cfg.init_field)
        field = layer_cell_values(
            layer, str(cfg.init_field), file_rest=animation.file_points(animation.rest_vertices),
            file_vertices=animation.file_vertices, rest=animation.rest_vertices,
            points=np.asarray(problem.mesh.points), cells=np.asarray(problem.mesh.cells))
    except MeshError as err:
        raise setting_error("init_field", cfg.init_field, str(err)) from err
    parameterization = problem.parameterization
    target = torch.as_tensor(field, dtype=problem.dtype, device=problem.device)
    basis = parameterization.basis
    if basis is None:
        values = target
    else:
        dense = (basis.to_dense() if basis.layout != torch.strided else basis).to(target)
        values = torch.linalg.lstsq(dense, target[:, None]).solution[:, 0]
    values = torch.clamp(values, min=FLOOR * float(target.mean()))
    return torch.log(values) if parameterization.transform == "exp" else values
