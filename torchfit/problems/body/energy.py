"""The rigged body's energy: the one place where the terms both of its simulations see are built.

:func:`body_energy` returns the physics model of a body's tetrahedra (a
:class:`~torchfit.physics.elasticity.SimplicialElasticity`: the constitutive model's
strain energy, its residual ``R = dE/dx`` and tangent on the mesh's pattern, linear in the
Young's modulus field). Every simulation of the body takes this one model: the equilibrium
per frame (:class:`~.poses.FramePoses` through
:class:`~torchfit.physics.elasticity.QuasistaticElasticity`), the body in time (the
:class:`~torchfit.physics.dynamics.DynamicSystem` of :class:`~.dynamic.BodyInTime`, whose
implicit step adds inertia and damping to it), the start in time and the model comparison
(another constitutive model, the same terms). A new energy term (contact at the folds, a
collider) joins the body here, once: docs/guide/extending.md, "An energy term".
"""
from __future__ import annotations

import numpy as np
import torch

from ...physics.elasticity import SimplicialElasticity


def body_energy(points: np.ndarray, cells: np.ndarray, model: str, nu: float,
                dtype: torch.dtype, device: torch.device) -> SimplicialElasticity:
    """The energy of a body's tetrahedra ``cells`` ``(n_tets, 4)`` at rest positions
    ``points`` ``(n, 3)`` (metres) with the constitutive ``model`` (``linear``,
    ``corotated``, ``stable_neo_hookean``) and Poisson ratio ``nu``: its parameters are one
    Young's modulus per tetrahedron ``(n_tets,)``."""
    return SimplicialElasticity(torch.from_numpy(points), torch.from_numpy(cells), model, nu=nu,
                                dtype=dtype, device=device)
