"""The rigged body simulated with another constitutive model (the model comparison).

:class:`ModelComparison` is a collaborator of the body: it holds the body's mesh, driven
vertices and backend, builds each other model's quasistatic solver once (cold-started from
the animated pose, ``start="rest"``) and simulates it without gradient; the body's own model
is the body's own simulation (``own``). The body in time has no comparison (quasistatic).
"""
from __future__ import annotations

from typing import Any, Callable

import torch
from torch import Tensor

from ...mesh import SimplexMesh
from ...physics import NewtonOptions
from ...physics.elasticity import QuasistaticElasticity
from .energy import body_energy


class ModelComparison:
    """Other constitutive models on the same body, rig and field.

    Args:
        mesh: the body's tetrahedral mesh.
        driven: ``(n_driven,)`` tetrahedron vertices the rig prescribes.
        backend: the linear-solve backend of the body's own model.
        settings: the body's settings (``model``, ``dynamic``, ``nu``, ``newton_max_iter``,
            ``newton_rtol``, ``newton_atol``).
        dtype, device: the body's.
        drive, start: the driven positions ``(F, n_driven, 3)`` and skinned poses ``(F, n,
            3)`` of the fitted frames.
        own: the body's own simulation of every fitted frame (``E -> (F, n, 3)``).
    """

    def __init__(self, mesh: SimplexMesh, driven: Any, backend: Any, settings: Any,
                 dtype: torch.dtype, device: torch.device, drive: Tensor, start: Tensor,
                 own: Callable[[Tensor], Tensor]) -> None:
        self.mesh, self.driven, self.backend, self.settings = mesh, driven, backend, settings
        self.dtype, self.device = dtype, device
        self.drive, self.start, self.own = drive, start, own
        self.models: dict[str, QuasistaticElasticity] = {}   # built once per model

    def simulate_model(self, model: str, E: Tensor, frames: list[int] | None = None) -> Tensor:
        """Positions ``(len(frames), n_vertices, 3)`` of the same body, rig and field with
        another constitutive ``model`` (all fitted frames by default), no gradient; the
        body's own model returns the body's own simulation."""
        if self.settings.dynamic:
            raise NotImplementedError("the model comparison is quasistatic: the dynamic body "
                                      "has none")
        frames = list(range(self.drive.shape[0])) if frames is None else list(frames)
        if model == self.settings.model.value:
            with torch.no_grad():
                return self.own(E.detach())[frames]
        index = torch.as_tensor(frames, device=self.device)
        return self.simulate(model, E, self.drive[index], self.start[index])

    def solver(self, model: str) -> QuasistaticElasticity:
        """The quasistatic solver of ``model`` (built on first use)."""
        if model not in self.models:
            cfg = self.settings
            elastic = body_energy(self.mesh.points, self.mesh.cells, model, cfg.nu, self.dtype,
                                  self.device)
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
