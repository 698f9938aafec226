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
collider) joins the body here, once: docs/guide/extending.md, "An energy term"; the
self-contact barrier (``problem.contact``) is the first.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ...physics.contact import ContactInputError, ElasticityWithContact, SelfContact
from ...physics.elasticity import SimplicialElasticity
from ..config import ProblemConfigError, require_setting

#: the largest barrier reach (fraction of the diagonal): beyond it the barrier pushes apart
#: surfaces that are not near contact at all
MAX_CONTACT_DHAT = 0.1


def check_contact_settings(cfg: Any) -> None:
    """``problem.contact_dhat`` in ``(0, MAX_CONTACT_DHAT]``, and no contact in time yet (one
    line naming the setting)."""
    require_setting(0 < cfg.contact_dhat <= MAX_CONTACT_DHAT, cfg, "contact_dhat",
                    f"must be in (0, {MAX_CONTACT_DHAT:g}]: the contact distance as a fraction of "
                    "the body's diagonal (1e-3 reaches 1 mm on a 1 m body)")
    # the body in time reads the elastic tangent's element blocks (DynamicSystem) and its
    # step's Newton has no collision-free cap yet
    require_setting(not (cfg.contact and getattr(cfg, "dynamic", False)), cfg, "contact",
                    "is not yet available with problem.dynamic=true (the body in time); set "
                    "problem.contact=false")


def body_energy(points: np.ndarray, cells: np.ndarray, model: str, nu: float,
                dtype: torch.dtype, device: torch.device, contact_dhat: float | None = None,
                modulus: float = 1.0) -> SimplicialElasticity | ElasticityWithContact:
    """The energy of a body's tetrahedra ``cells`` ``(n_tets, 4)`` at rest positions
    ``points`` ``(n, 3)`` (metres) with the constitutive ``model`` (``linear``,
    ``corotated``, ``stable_neo_hookean``) and Poisson ratio ``nu``: its parameters are one
    Young's modulus per tetrahedron ``(n_tets,)``.

    With ``contact_dhat`` (``problem.contact``: the barrier's reach as a fraction of the
    diagonal) the sum of that elastic model and the IPC self-contact of the tetrahedra's
    boundary surface (:class:`~torchfit.physics.contact.ElasticityWithContact`), its barrier
    stiffness set from the elastic tangent at rest for a uniform ``modulus`` (the initial
    guess, in the parameters' units); without it the elastic model alone (the term is
    absent, not zero: the results are bit for bit those without contact).
    Raises :class:`ProblemConfigError` for a rest surface that passes through itself.
    """
    elastic = SimplicialElasticity(torch.from_numpy(points), torch.from_numpy(cells), model,
                                   nu=nu, dtype=dtype, device=device)
    if contact_dhat is None:
        return elastic
    try:
        contact = SelfContact(points, cells, contact_dhat)
    except ContactInputError as error:
        raise ProblemConfigError(str(error)) from None
    with torch.no_grad():
        rest = torch.as_tensor(points, dtype=torch.float64).reshape(1, -1)
        E = torch.full((elastic.n_cells,), float(modulus), dtype=dtype, device=device)
        x = rest.to(dtype=dtype, device=device)
        values = elastic.tangent_pattern.assemble(elastic.tangent_values(x, E))[0]
        diagonal = elastic.tangent_pattern.diagonal(values)
        gradient = elastic.residual(x, E)[0].cpu().numpy()
    contact.initial_stiffness(gradient, x.cpu().to(torch.float64),
                              float(diagonal.mean()))
    return ElasticityWithContact(elastic, contact)
