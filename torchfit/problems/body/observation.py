"""What a rigged body observes: the user's surface vertices, embedded in its tetrahedra.

A :class:`SurfaceObservation` is built once per body from the animation and the barycentric
embedding of its surface vertices in the tetrahedral mesh. Every vertex is observed but the
ones the animation marks as driven (their motion is the rig's, not data). Contracts:

- positions ``x`` are tetrahedron vertex positions ``(..., n, 3)`` in metres;
- ``observe(x)`` is frame-major ``(F * n_obs * 3,)``, the rows of :meth:`matrix`;
- ``surface(x)`` maps to every surface vertex of the user's file ``(..., V, 3)``;
- the clean target is the animation (``target=rig``) or the synthetic truth's surface
  (``x_true`` given): :meth:`clean_targets`, :meth:`clean_surface`;
- the sparse observation matrix is cached per dtype and device (one at a time).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ...mesh import Animation, Embedding, dof_matrix
from .report import surface_distances


class SurfaceObservation:
    """The observed surface vertices of a body and the distances to their targets.

    Args:
        animation: the fitted frames (their surface, driven marks and target positions).
        embedding: the user's surface vertices in the tetrahedra (cells, weights).
        cells: the tetrahedra ``(n_tets, 4)``.
        n_vertices: tetrahedron vertices.
        dtype, device: of the targets and weights.
    """

    def __init__(self, animation: Animation, embedding: Embedding, cells: np.ndarray,
                 n_vertices: int, dtype: torch.dtype, device: torch.device) -> None:
        if animation.driven is not None:
            observed = np.flatnonzero(~animation.driven.mask)
        else:
            observed = np.arange(animation.n_vertices)
        #: the observed surface vertices ``(n_obs,)`` (indices into the user's vertices)
        self.vertices = torch.as_tensor(observed)
        self.embedding = embedding
        self.frames = animation.frames
        self.n_vertices = int(n_vertices)
        self.dtype, self.device = dtype, device
        self._weights = torch.as_tensor(embedding.weights[observed], dtype=dtype, device=device)
        self._corners = torch.as_tensor(cells[embedding.cells[observed]], device=device)
        self._matrix: Tensor | None = None
        self._matrix_key: tuple[torch.dtype, torch.device] | None = None

    def surface(self, x: Tensor) -> Tensor:
        """The user's surface vertices ``(..., V_surface, 3)`` of tet positions ``(..., n, 3)``."""
        return self.embedding.apply(x)

    def __call__(self, x: Tensor) -> Tensor:
        """The observed surface vertices of every frame, frame-major ``(F * n_obs * 3,)``."""
        corners = self._corners.to(x.device)
        weights = self._weights.to(x)
        return (x[..., corners, :] * weights[..., None]).sum(-2).reshape(-1)

    def matrix(self, like: Tensor) -> Tensor:
        """The observed rows of the embedding on the flat dofs, sparse
        ``(n_obs 3, n_vertices 3)`` (rows and columns point-major, as :meth:`__call__`),
        in ``like``'s dtype and device (cached)."""
        key = (like.dtype, like.device)
        if self._matrix is None or self._matrix_key != key:
            self._matrix = dof_matrix(self._corners.cpu(), self._weights.cpu(), self.n_vertices,
                                      3).to(like)
            self._matrix_key = key
        return self._matrix

    def measured(self) -> Tensor:
        """The animation's observed vertices in every frame, frame-major ``(F n_obs 3,)``."""
        frames = torch.as_tensor(self.frames, dtype=self.dtype, device=self.device)
        return frames[:, self.vertices.to(self.device), :].reshape(-1)

    def clean_targets(self, x_true: Tensor | None) -> Tensor:
        """Noise-free targets ``(F, n_obs, 3)``: the synthetic truth's (``x_true``), or the
        animation's."""
        if x_true is not None:
            return self(x_true).reshape(x_true.shape[0], -1, 3)
        return torch.as_tensor(self.frames, dtype=self.dtype, device=self.device)[
            :, self.vertices.to(self.device)]

    def clean_surface(self, x_true: Tensor | None) -> Tensor:
        """Noise-free target surface of every user vertex ``(F, V, 3)`` (observed or not)."""
        if x_true is not None:
            return self.surface(x_true)
        return torch.as_tensor(self.frames, dtype=self.dtype, device=self.device)

    def surface_errors(self, x: Tensor, x_true: Tensor | None) -> Tensor:
        """Distance of every observed surface vertex to its noise-free target ``(F, n_obs)``."""
        return surface_distances(self(x).reshape(x.shape[0], -1, 3), self.clean_targets(x_true))

    def surface_error_field(self, x: Tensor, x_true: Tensor | None) -> Tensor:
        """Distance of every user surface vertex to its noise-free target ``(F, V)``."""
        with torch.no_grad():
            return surface_distances(self.surface(x), self.clean_surface(x_true))
