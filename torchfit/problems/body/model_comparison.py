"""The rigged body simulated with another constitutive model (the model comparison).

:class:`ModelComparison` is a collaborator of the body: it holds the body's mesh, driven
vertices and backend, builds each other model's quasistatic solver once (cold-started from
the animated pose, ``start="rest"``) and simulates it without gradient.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ...mesh import SimplexMesh
from ...physics import NewtonOptions
from ...physics.elasticity import QuasistaticElasticity, SimplicialElasticity


class ModelComparison:
    """Other constitutive models on the same body, rig and field.

    Args:
        mesh: the body's tetrahedral mesh.
        driven: ``(n_driven,)`` tetrahedron vertices the rig prescribes.
        backend: the linear-solve backend of the body's own model.
        settings: the body's settings (``nu``, ``newton_max_iter``, ``newton_rtol``,
            ``newton_atol``).
        dtype, device: the body's.
    """

    def __init__(self, mesh: SimplexMesh, driven: Any, backend: Any, settings: Any,
                 dtype: torch.dtype, device: torch.device) -> None:
        self.mesh, self.driven, self.backend, self.settings = mesh, driven, backend, settings
        self.dtype, self.device = dtype, device
        self.models: dict[str, QuasistaticElasticity] = {}   # built once per model

    def solver(self, model: str) -> QuasistaticElasticity:
        """The quasistatic solver of ``model`` (built on first use)."""
        if model not in self.models:
            cfg = self.settings
            elastic = SimplicialElasticity(torch.from_numpy(self.mesh.points),
                                           torch.from_numpy(self.mesh.cells), model, nu=cfg.nu,
                                           dtype=self.dtype, device=self.device)
            newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                                   atol=cfg.newton_atol)
            self.models[model] = QuasistaticElasticity(elastic, self.driven,
                                                       backend=self.backend, newton=newton,
                                                       start="rest")
        return self.models[model]

    def simulate(self, model: str, E: Tensor, drive: Tensor, start: Tensor) -> Tensor:
        """Positions ``(P, n_vertices, 3)`` with ``model`` and field ``E`` ``(n_tets,)`` for
        the driven positions ``drive`` ``(P, n_driven, 3)`` from ``start`` ``(P, n, 3)``,
        no gradient."""
        with torch.no_grad():
            return self.solver(model)(E.detach(), drive.to(E), x_init=start.to(E))
