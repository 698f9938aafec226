"""The quasistatic body's simulation: every fitted frame an independent equilibrium of its pose.

:class:`FramePoses` is the :class:`~torchfit.problems.protocols.BodySimulation` of a rigged
body with ``problem.dynamic=false``. The rig prescribes the driven tetrahedron vertices of
every frame; the others are at the equilibrium of the field ``E (n_tets,)`` (Pa, or relative
to ``problem.E0``: the data are scale-free), found by Newton from the skinned pose or warm
started from the last solution (:class:`~torchfit.physics.elasticity.QuasistaticElasticity`).
Frames that repeat a pose are simulated once (:mod:`.repeated_poses`): ``simulated_poses()``
is the index of the distinct poses, ``repeated_poses[1]`` the pose of every frame.

The seam a distributed run plugs into is :meth:`FramePoses.plug`: another
:class:`~torchfit.problems.protocols.PoseSimulation` for the distinct poses (a split over
ranks) and, on the leader, where the observed Jacobian comes from. Warm starts, the cold
blocks (``independent()``) and the state a checkpoint keeps are the pose simulation's
equilibrium's (:attr:`FramePoses.warm_starts`).
"""
from __future__ import annotations

import contextlib
from typing import Any, Callable, ContextManager

import torch
from torch import Tensor

from ...params import Parameterization
from ..config import ProblemConfigError
from ..protocols import PoseSimulation, WarmStarts
from .setup import first_simulation


class FramePoses:
    """The equilibrium per frame of a rigged body's distinct poses.

    Args:
        quasistatic: the pose simulation of this process (a ``QuasistaticElasticity`` on
            the body's model, driven vertices and backend).
        drive: driven vertex positions of every fitted frame ``(F, n_driven, 3)``.
        start: the skinned pose of every fitted frame ``(F, n, 3)`` (Newton's cold start).
        repeated_poses: ``(first frame of each distinct pose (P,), pose of each frame (F,))``
            or ``None`` (every frame its own pose).
        model: the constitutive model's name (the first simulation's progress line).
        n_tets: tetrahedra (the field's length).
    """

    def __init__(self, quasistatic: PoseSimulation, drive: Tensor, start: Tensor,
                 repeated_poses: tuple[Tensor, Tensor] | None, model: str, n_tets: int) -> None:
        #: the pose simulation in use: this process's, or what :meth:`plug` plugged in
        self.quasistatic = quasistatic
        self.drive, self.start = drive, start
        self.repeated_poses = repeated_poses
        self.model_name, self.n_tets = model, int(n_tets)
        #: where :meth:`jacobian` comes from when a distributed run gave one
        self.jacobian_provider: Callable[[Tensor], Any] | None = None
        self._simulated = False         # the first simulation's progress lines are shown

    # -- warm starts: those of the pose simulation in use (what a run plugged in too) --------
    @property
    def warm_starts(self) -> WarmStarts:
        """Itself: :class:`~torchfit.problems.protocols.WarmStarts` that follow the pose
        simulation in use (a distributed split plugged in later included)."""
        return self

    def independent(self) -> ContextManager[None]:
        """Cold starts from the animated pose that seed no warm start (the synthetic
        target, the homogeneous baseline)."""
        return self.quasistatic.equilibrium.independent()

    def warm_start_state(self) -> dict[str, Any]:
        """The solutions Newton's next warm start reads (the anchor, the most recent one)."""
        return self.quasistatic.equilibrium.warm_start_state()

    def restore_warm_start_state(self, state: dict[str, Any], device: Any = None) -> None:
        self.quasistatic.equilibrium.restore_warm_start_state(state, device)

    def plug(self, simulation: PoseSimulation,
             jacobian: Callable[[Tensor], Any] | None = None) -> None:
        """The seam a distributed run plugs into: simulate the poses with ``simulation``
        from now on and, where given, take :meth:`jacobian` from ``jacobian`` (``theta ->
        (m, n_params)`` rows, or a handle with the products the dense path forms:
        ``torchfit.run.distributed``)."""
        self.quasistatic = simulation
        self.jacobian_provider = jacobian

    def simulated_poses(self) -> Tensor | slice:
        """The frames simulated (the first of each distinct pose): an index ``(P,)``, or
        every frame."""
        return slice(None) if self.repeated_poses is None else self.repeated_poses[0]

    def simulate(self, E: Tensor) -> Tensor:
        """Tetrahedron vertex positions ``(F, n, 3)`` of every fitted frame for ``E``
        ``(n_tets,)``: each distinct pose once, then every frame."""
        if E.shape != (self.n_tets,):
            raise ProblemConfigError(f"Young's modulus must have shape ({self.n_tets},) "
                                     f"(one per tetrahedron), got {tuple(E.shape)}")
        poses = self.simulated_poses()
        drive, start = self.drive[poses], self.start[poses]
        with contextlib.nullcontext() if self._simulated else \
                first_simulation(len(drive), self.n_tets, self.model_name):
            x = self.quasistatic(E, drive.to(E), x_init=start.to(E))
        self._simulated = True
        return x if self.repeated_poses is None else x[self.repeated_poses[1]]

    def pose_jacobian(self, theta: Tensor, parameterization: Parameterization,
                      observe: Callable[[Tensor], Tensor]) -> Tensor:
        """``(P, n_obs 3, n_params)`` of each simulated pose: every parameter direction a
        right-hand side of the pose's one factorisation, the observation ``observe(like)``
        (sparse ``(n_obs 3, n 3)``) applied to its columns as soon as they are solved (no
        ``(F, V, 3, n)``)."""
        E = parameterization(theta.detach())
        directions = parameterization.jacobian(theta.detach())          # (n_cells, n)
        poses = self.simulated_poses()
        return self.quasistatic.jacobian(E, self.drive[poses].to(E), directions,
                                         x_init=self.start[poses].to(E), observe=observe(E))

    def jacobian(self, theta: Tensor, parameterization: Parameterization,
                 observe: Callable[[Tensor], Tensor]) -> Tensor:
        """``d observe(simulate(map(theta))) / d theta`` ``(m, n_params)``: every frame's
        rows of :meth:`pose_jacobian` (or the :attr:`jacobian_provider`'s)."""
        if self.jacobian_provider is not None:
            return self.jacobian_provider(theta)
        observed = self.pose_jacobian(theta, parameterization, observe)
        if self.repeated_poses is not None:
            observed = observed[self.repeated_poses[1]]
        return observed.reshape(-1, observed.shape[-1])                 # (F n_obs 3, n)

    def material_density(self, physical: Tensor) -> tuple[float, str] | None:
        """``None``: a quasistatic body does not determine its density (the outputs assume
        one)."""
        return None
