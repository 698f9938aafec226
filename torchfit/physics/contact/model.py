"""A body's energy as a sum of terms: the elastic model plus the self-contact barrier.

:class:`ElasticityWithContact` is the sum the receiver (``body_energy``) declares: it is an
:class:`~torchfit.physics.EquilibriumModel` whose energy, residual and tangent are the
elastic model's plus the :class:`~.barrier.SelfContact` term's, and whose parameter
derivative is the elastic model's alone (the barrier depends on positions only). Anything
else (``rest``, ``n_cells``, ``material``, ``check_modulus``...) is the elastic model's.

The tangent's pattern is a union pattern that grows: the elastic pattern plus one 3x3 block
for every pair of body vertices that an active contact has coupled in any frame so far. A
pair that appears for the first time builds a new pattern (``pattern_builds`` counts them;
each is one new symbolic analysis of the reduced tangent by the backend); pairs are never
dropped, so the contacts of a fold that open and close again cost no new analysis. The
contributions are the elastic ones followed by ``(n_pairs, 3, 3)`` contact blocks.

``collision_free_step(x0, x1)`` is the hook Newton's line search asks before it backtracks
(the largest step free of collisions, ipctk's CCD), and ``after_step(x)`` adapts the barrier
stiffness as IPC does after each Newton iteration.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ...linalg import SparsePattern
from .barrier import ContactInputError, SelfContact


class ElasticityWithContact:
    """The sum of an elastic model ``elastic`` (a 3-D ``SimplicialElasticity``) and the
    self-contact term ``contact`` on the same vertices."""

    symmetric = True
    linear = False
    frame_independent = True

    def __init__(self, elastic, contact: SelfContact) -> None:
        if contact.n_dofs != elastic.n_dofs:
            raise ValueError(f"the contact term has {contact.n_dofs} dofs, the elastic model "
                             f"{elastic.n_dofs}")
        self.elastic = elastic
        self.contact = contact
        self.n_dofs = elastic.n_dofs
        self.dim = elastic.dim
        self.pairs = np.zeros((0, 2), dtype=np.int64)    # sorted by (a, b), a and b both ways
        self.pattern_builds = 0
        self.start_substeps = 0       # equilibria solved by stepped_start
        self.tangent_pattern: SparsePattern = elastic.tangent_pattern

    def __getattr__(self, name: str):
        # only reached for names this class does not define: the elastic model's own
        if name == "elastic":
            raise AttributeError(name)
        return getattr(self.elastic, name)

    # -- energy and residual ---------------------------------------------------------------
    def energy(self, x: Tensor, E: Tensor) -> Tensor:
        return self.elastic.energy(x, E) + self.contact.energy(x).to(x)

    def residual(self, x: Tensor, E: Tensor) -> Tensor:
        return self.elastic.residual(x, E) + self.contact.gradient(x).to(x)

    def residual_and_energy(self, x: Tensor, E: Tensor) -> tuple[Tensor, Tensor]:
        residual, energy = self.elastic.residual_and_energy(x, E)
        return (residual + self.contact.gradient(x).to(x),
                energy + self.contact.energy(x).to(energy))

    def forces(self, x: Tensor, E: Tensor) -> Tensor:
        return -self.residual(x, E)

    def param_derivative(self, x: Tensor, E: Tensor):
        """The elastic model's ``dR/dE``: the barrier has no material parameter."""
        return self.elastic.param_derivative(x, E)

    # -- tangent ------------------------------------------------------------------------------
    def tangent_values(self, x: Tensor, E: Tensor, projected: bool = False) -> Tensor:
        """Contributions ``(F, n_contrib)`` on the current union pattern: the elastic ones,
        then the contact blocks (exact, or each pair's Hessian projected to PSD)."""
        elastic = self.elastic.tangent_values(x, E, projected)
        hessians, new_pairs = [], []
        for V in self.contact.surface_positions(x):
            H, pairs = self.contact.hessian_and_pairs(V, projected)
            hessians.append(H)
            new_pairs.append(pairs)
        self._grow(np.concatenate([self.pairs, *new_pairs]))
        n_pairs = self.pairs.shape[0]
        blocks = np.zeros((x.shape[0], n_pairs * 9))
        if n_pairs:
            n = self.contact.n_vertices
            keys = self.pairs[:, 0] * n + self.pairs[:, 1]
            dofs = self.contact.surface_dofs
            for f, H in enumerate(hessians):
                rows, cols = dofs[H.row], dofs[H.col]
                pair = np.searchsorted(keys, (rows // 3) * n + cols // 3)
                np.add.at(blocks[f], pair * 9 + (rows % 3) * 3 + cols % 3, H.data)
        elastic = elastic.expand(x.shape[0], -1)
        return torch.cat([elastic, torch.from_numpy(blocks).to(elastic)], dim=1)

    def _grow(self, pairs: np.ndarray) -> None:
        """Make the union pattern hold every vertex pair of ``pairs`` ``(p, 2)``."""
        pairs = np.unique(pairs, axis=0) if pairs.size else pairs
        if pairs.shape[0] == self.pairs.shape[0]:
            return
        self.pairs = pairs
        base = self.elastic.tangent_pattern
        elastic_rows = base.row_indices[base.scatter].cpu()
        elastic_cols = base.col_indices[base.scatter].cpu()
        local = torch.arange(3)
        a = torch.from_numpy(pairs[:, 0])[:, None, None] * 3 + local[None, :, None]
        b = torch.from_numpy(pairs[:, 1])[:, None, None] * 3 + local[None, None, :]
        rows = a.expand(-1, 3, 3).reshape(-1)
        cols = b.expand(-1, 3, 3).reshape(-1)
        self.tangent_pattern = SparsePattern(torch.cat([elastic_rows, rows]),
                                             torch.cat([elastic_cols, cols]),
                                             (self.n_dofs, self.n_dofs))
        self.pattern_builds += 1

    # -- the line search's hooks -------------------------------------------------------------
    def collision_free_step(self, x0: Tensor, x1: Tensor) -> Tensor:
        """The largest step ``(F,)`` in ``[0, 1]`` from ``x0`` towards ``x1`` free of contact."""
        return self.contact.collision_free_step(x0, x1)

    def collision_free_start(self, start: Tensor, fixed_dofs: Tensor) -> tuple[Tensor, list[int]]:
        """Newton's starts ``(F, n_dofs)`` that do not pass through themselves: ``start``
        where its surface is free, else the rest shape with the Dirichlet dofs ``fixed_dofs``
        moved to ``start``'s, carried towards ``start`` as far as no contact is crossed (a
        skinned pose often passes through itself at a fold, and IPC's line search must
        start from a state without intersections). Also returns the frames where that moved
        rest shape passes through itself too (their start is left as it was): for
        :meth:`stepped_start`."""
        crossed = self.contact.intersecting_frames(start)
        if not crossed:
            return start, []
        frames = torch.as_tensor(crossed, device=start.device)
        target = start[frames]
        moved = self.elastic.rest.points.reshape(1, -1).to(target).expand_as(target).clone()
        fixed = torch.as_tensor(fixed_dofs, device=start.device)
        moved[:, fixed] = target[:, fixed]
        alpha = self.contact.collision_free_step(moved, target).to(target)
        out = start.clone()
        out[frames] = moved + alpha[:, None] * (target - moved)
        stuck = self.contact.intersecting_frames(moved)
        for i in stuck:
            out[crossed[i]] = start[crossed[i]]
        return out, [crossed[i] for i in stuck]

    def stepped_start(self, solve: Callable[[Tensor], Tensor], free_state: Tensor,
                      free_pose: Tensor, target_pose: Tensor, fixed_dofs: Tensor,
                      substeps: int = 8, max_substeps: int = 256) -> Tensor:
        """A start without intersections for a frame whose animated pose ``target_pose``
        ``(1, n_dofs)`` passes through itself: from ``free_state`` (an equilibrium without
        intersections of the frame whose animated pose is ``free_pose``), the Dirichlet dofs
        ``fixed_dofs`` follow the animated motion ``target_pose - free_pose`` in substeps (the
        free dofs start where the last equilibrium left them: moving them with the animation
        pushes them into the barrier, and Newton creeps out); each substep's move is checked
        by CCD (halved where it would cross a contact) and then solved to equilibrium with
        contact by ``solve(x_start) -> x`` (the Dirichlet dofs as ``x_start``'s; a solved
        substep lets the next one grow back). Returns the
        last equilibrium (its Dirichlet dofs are ``target_pose``'s). Raises
        :class:`~.barrier.ContactInputError` when a substep below ``1 / max_substeps`` of
        the motion still crosses."""
        fixed = torch.as_tensor(fixed_dofs, device=target_pose.device)
        delta = torch.zeros_like(target_pose)
        delta[:, fixed] = target_pose[:, fixed] - free_pose[:, fixed]
        x, done, h = free_state, 0.0, 1.0 / substeps
        while done < 1.0 - 1e-12:
            h = min(h, 1.0 - done)
            candidate = x + h * delta
            if float(self.contact.collision_free_step(x, candidate)[0]) < 1.0:
                h /= 2
                if h < 1.0 / max_substeps:
                    raise ContactInputError("no start without intersections: the animated "
                                            "motion crosses a contact")
                continue
            x = solve(candidate)
            done += h
            self.start_substeps += 1
            h = min(2 * h, 1.0 / substeps)      # the barrier reopened the gap: longer again
        return x

    def after_step(self, x: Tensor) -> None:
        """Adapt the barrier stiffness after a Newton iteration (IPC's rule)."""
        self.contact.adapt_stiffness(x)

    def __repr__(self) -> str:
        return (f"ElasticityWithContact({self.elastic!r}, dhat={self.contact.dhat:.3g} m, "
                f"kappa={self.contact.stiffness:.3g})")
