"""The rigged body simulated with another constitutive model (the model comparison).

:func:`simulate_with_model` reuses the body's mesh, rig and field; the other model's
quasistatic solver is built once per model and kept on the problem (``other_models``),
cold-started from the animated pose (``start="rest"``), without gradient.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ...physics import NewtonOptions
from ...physics.elasticity import QuasistaticElasticity, SimplicialElasticity


def simulate_with_model(problem: Any, model: str, E: Tensor,
                        frames: list[int] | None = None) -> Tensor:
    """Positions ``(len(frames), n_vertices, 3)`` of the rigged body ``problem`` with the
    constitutive ``model`` and field ``E`` ``(n_tets,)`` (all frames by default); the fit's
    own model returns the fit's simulation (its state, warm starts included)."""
    frames = list(range(problem.n_frames)) if frames is None else list(frames)
    if model == problem.cfg.model.value:
        with torch.no_grad():
            return problem.simulate(E.detach())[frames]
    others: dict[str, QuasistaticElasticity] = problem.other_models
    if model not in others:
        cfg = problem.cfg
        other = SimplicialElasticity(torch.from_numpy(problem.mesh.points),
                                     torch.from_numpy(problem.mesh.cells), model, nu=cfg.nu,
                                     dtype=problem.dtype, device=problem.device)
        newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                               atol=cfg.newton_atol)
        others[model] = QuasistaticElasticity(other, problem.dirichlet_vertices,
                                              backend=problem.backend, newton=newton,
                                              start="rest")
    index = torch.as_tensor(frames, device=problem.device)
    with torch.no_grad():
        return others[model](E.detach(), problem.dirichlet_positions[index].to(E),
                             x_init=problem.start_positions[index].to(E))
