"""The shape shared by every canonical problem: ``y = observe(simulate(map(theta)))``.

A problem owns the mesh, the true field, the data (with seeded noise), the
observation and the metrics of PROBLEMS.md. It contains no solver logic: solvers get
:meth:`InverseProblem.residual`, nothing else.
"""
from __future__ import annotations

import math
from typing import Any, Protocol, Sequence, runtime_checkable

import torch
from torch import Tensor

from ..params import Parameterization
from ..residual import ResidualFunction


class ProblemConfigError(ValueError):
    """A problem setting is invalid; the message names the setting and what to do."""


def require(condition: bool, message: str) -> None:
    if not condition:
        raise ProblemConfigError(message)


def check_finite_targets(targets: Tensor, frame_of: Tensor, node_of: Tensor,
                         what: str = "target") -> None:
    """Raise naming the first frame and node whose target is NaN or infinite.

    Args:
        targets: ``(m,)`` observed values.
        frame_of, node_of: ``(m,)`` frame and node index of every observed value.
    """
    bad = ~torch.isfinite(targets)
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0])
        raise ProblemConfigError(
            f"{what} of frame {int(frame_of[i])}, node {int(node_of[i])} is "
            f"{float(targets[i])}; {int(bad.sum())} non-finite value(s) in all; fix or drop "
            "them before fitting")


def add_noise(clean: Tensor, sigma: float, seed: int) -> tuple[Tensor, float | None]:
    """I.i.d. Gaussian noise of standard deviation ``sigma`` (seeded, on the CPU generator).

    Returns:
        ``(noisy, delta)`` with ``delta = sigma * sqrt(m)`` the noise level handed to
        the discrepancy principle, ``None`` when ``sigma == 0``.
    """
    if sigma == 0:
        return clean.clone(), None
    generator = torch.Generator().manual_seed(int(seed))
    noise = torch.randn(clean.shape, generator=generator, dtype=clean.dtype).to(clean.device)
    return clean + sigma * noise, sigma * math.sqrt(clean.numel())


@runtime_checkable
class FieldImageProblem(Protocol):
    """A problem whose field can be drawn as a 2-D image (poisson2d, membrane2d)."""

    def field_image(self, field: Tensor) -> Any:
        """``(n_field,)`` values -> ``(H, W)`` array, row 0 at the top."""


@runtime_checkable
class FramedProblem(Protocol):
    """A problem with several frames (load cases, animation frames) and per-frame errors."""

    n_frames: int
    default_sheet_frame: int

    def frame_errors(self, x: Tensor) -> dict[str, Any]:
        """``{'u_err_inf': (F,), 'u_err_2': (F,)}`` of the state ``x`` against the truth."""

    def frame_names(self) -> list[str]:
        """One short label per frame."""


@runtime_checkable
class MeshProblem(Protocol):
    """A problem on a simplicial mesh (``mesh.points``, ``mesh.cells``, ``mesh.extent``)."""

    mesh: Any


class InverseProblem:
    """Base class; subclasses set the attributes below in ``__init__``.

    Attributes:
        name: the config name (``spring1d``, ...).
        parameterization: ``theta -> field``.
        theta0: ``(n_params,)`` initial guess.
        field_true: true field ``(n_field,)`` or ``None`` (user data).
        x_true: noise-free state of the true field, ``(F, n_nodes, dim)`` or ``None``.
        data: ``(m,)`` targets ``y_t``.
        noise_level: ``delta`` or ``None``.
        scale_free: data never fix the global scale of the field.
    """

    name: str = "problem"
    field_name: str = "k"
    parameterization: Parameterization
    theta0: Tensor
    field_true: Tensor | None
    x_true: Tensor | None
    data: Tensor
    noise_level: float | None
    scale_free: bool = False

    # -- to implement -----------------------------------------------------------------
    def simulate(self, field: Tensor) -> Tensor:
        """All node positions of all frames, ``(F, n_nodes, dim)``."""
        raise NotImplementedError

    def observe(self, x: Tensor) -> Tensor:
        """Linear sampling of the state: ``(F, n_nodes, dim) -> (m,)``."""
        raise NotImplementedError

    # -- shared -----------------------------------------------------------------------
    def forward(self, theta: Tensor) -> Tensor:
        """``observe(simulate(map(theta)))``, ``(m,)``."""
        return self.observe(self.simulate(self.parameterization(theta)))

    def residual(self) -> ResidualFunction:
        gauge = self.parameterization.scale_direction if self.scale_free else None
        return ResidualFunction(self.forward, self.data, self.noise_level, gauge)

    def field(self, theta: Tensor) -> Tensor:
        return self.parameterization(theta.detach())

    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        """The metrics of PROBLEMS.md at ``theta`` (state errors on every node and frame)."""
        with torch.no_grad():
            field = self.field(theta)
            if x is None:
                x = self.simulate(field)
            out: dict[str, float] = {
                "misfit": float(torch.linalg.vector_norm(self.observe(x) - self.data))}
            if self.x_true is not None:
                du = (x - self.x_true).reshape(-1)
                out["u_err_inf"] = float(du.abs().max())
                out["u_err_2"] = float(torch.linalg.vector_norm(du))
            if self.field_true is not None:
                truth = self.field_true
                dk = field - truth
                truth_norm = float(torch.linalg.vector_norm(truth))
                out["k_err_inf"] = float(dk.abs().max())
                out["k_err_2"] = float(torch.linalg.vector_norm(dk))
                out["k_err_rel"] = out["k_err_2"] / truth_norm
                if self.scale_free:
                    scale = float(torch.dot(field, truth) / torch.dot(field, field))
                    out["k_err_rel_aligned"] = float(
                        torch.linalg.vector_norm(scale * field - truth)) / truth_norm
        return out

    def describe(self) -> dict[str, object]:
        """Sizes for logs and result files."""
        return {"name": self.name, "n_params": self.parameterization.n_params,
                "n_data": int(self.data.numel()), "noise_level": self.noise_level,
                "scale_free": self.scale_free}


def node_frame_index(n_frames: int, nodes: Sequence[int] | Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """Frame and node of every entry of ``x[:, nodes, :].reshape(-1)``."""
    nodes_t = torch.as_tensor(nodes, dtype=torch.long)
    frame = torch.arange(n_frames).repeat_interleave(nodes_t.numel() * dim)
    node = nodes_t.repeat_interleave(dim).repeat(n_frames)
    return frame, node
