"""The interfaces of the problems layer: what a problem's collaborators offer it, and what the
reporting layer and the run may ask of a problem beyond the template.

Collaborators a problem owns (:class:`~torchfit.problems.base.InverseProblem` and the rigged
body compose them; each is passed in or built once, never patched):

- :class:`WarmStarts`: what later simulations carry over from earlier ones (cold blocks, the
  state a checkpoint keeps); an :class:`~torchfit.physics.Equilibrium` is one.
- :class:`TimeModel`: how the frames relate in time, independent equilibria
  (:data:`~torchfit.problems.dynamic.QUASISTATIC`) or one integration through time
  (:class:`~torchfit.problems.dynamic.TimeIntegration`): the simulation input beyond the
  field (the damping), its truth, metrics and description.
- :class:`PoseSimulation`: what simulates a rigged body's distinct poses (this process's
  quasistatic solver, or a distributed run's split of it over ranks).
- :class:`BodySimulation`: the rigged body's simulation, the equilibrium per frame
  (:class:`~torchfit.problems.body.poses.FramePoses`) or the implicit integrator through the
  shot (:class:`~torchfit.problems.body.dynamic.BodyInTime`).

Opt-in protocols the other layers test with ``isinstance`` (:class:`FieldImageProblem`,
:class:`FramedProblem`, :class:`MotionProblem`, :class:`MeshProblem`, :class:`BodyProblem`,
:class:`EmbeddedSurfaceProblem`, :class:`PosedProblem`): the base defines none of their members.
"""
from __future__ import annotations

from typing import Any, ContextManager, Protocol, runtime_checkable

from torch import Tensor

from ..params import Parameterization


# -- collaborators ---------------------------------------------------------------------------
@runtime_checkable
class WarmStarts(Protocol):
    """What the next simulations carry over from earlier ones, and how to block it.

    ``independent()``: a context whose simulations start cold and seed no later warm start
    (the synthetic target, baselines of reports); ``warm_start_state()``: the tensors the
    next simulations depend on besides their input (a checkpoint keeps them);
    ``restore_warm_start_state(state, device)``: put them back (a resume in another process).
    """

    def independent(self) -> ContextManager[None]:
        ...

    def warm_start_state(self) -> dict[str, Any]:
        ...

    def restore_warm_start_state(self, state: dict[str, Any], device: Any = None) -> None:
        ...


@runtime_checkable
class TimeModel(Protocol):
    """How a problem's frames relate in time (the simulation input beyond the field).

    ``in_time``: the frames are output times of one integration. ``parameterization(field)``
    the map ``theta -> simulation input`` around the field's (the damping scalars appended in
    time); ``field(physical)`` and ``scalars(physical)`` split a simulation input;
    ``true_input(field_true)`` the truth's simulation input; ``truth_settings()``,
    ``start_settings()`` the settings of its scalars' truth and start; ``metric_names()``,
    ``metrics(physical)`` and ``describe()`` what it adds to the problem's;
    ``accuracy(static)`` the relative accuracy of a simulation (``static``: the problem's
    own, when the frames are independent) and ``product_consistency()`` that of ``J^T w``
    against ``J v`` (``None``: exact transposes).
    """

    in_time: bool

    def parameterization(self, field: Parameterization) -> Parameterization:
        ...

    def field(self, physical: Tensor) -> Tensor:
        ...

    def scalars(self, physical: Tensor) -> Tensor:
        ...

    def true_input(self, field_true: Tensor) -> Tensor:
        ...

    def truth_settings(self) -> list[str]:
        ...

    def start_settings(self) -> list[str]:
        ...

    def metric_names(self) -> list[str]:
        ...

    def metrics(self, physical: Tensor) -> dict[str, float]:
        ...

    def describe(self) -> dict[str, Any]:
        ...

    def accuracy(self, static: float | None) -> float | None:
        ...

    def product_consistency(self) -> float | None:
        ...


class PoseSimulation(Protocol):
    """What a rigged body simulates its distinct poses with (:class:`BodySimulation`'s
    ``plug``): a :class:`~torchfit.physics.elasticity.QuasistaticElasticity`, or a distributed
    run's split of it over ranks.

    ``simulation(E, positions, x_init)``: positions ``(P, n, 3)`` of the poses whose driven
    vertices are at ``positions`` ``(P, n_driven, 3)``, from ``x_init`` ``(P, n, 3)``;
    ``jacobian(...)``: ``(P, rows, k)`` derivatives of the observed rows along ``k`` field
    directions; ``equilibrium``: cold blocks (``independent()``) and the warm-start state a
    checkpoint saves and a resume restores (:class:`WarmStarts`).
    """

    equilibrium: WarmStarts

    def __call__(self, E: Tensor, positions: Tensor, x_init: Tensor | None = None) -> Tensor:
        ...

    def jacobian(self, E: Tensor, positions: Tensor, directions: Tensor,
                 x_init: Tensor | None = None, observe: Tensor | None = None) -> Tensor:
        ...


#: the warm starts of a pose simulation (its ``equilibrium``)
PoseEquilibrium = WarmStarts


class BodySimulation(Protocol):
    """The rigged body's simulation: every fitted frame's tetrahedron vertex positions.

    ``simulate(physical)`` ``(F, n, 3)`` for the simulation input (``E (n_tets,)``, in time
    ``[E, alpha, beta(, density scale)]``); ``jacobian(physical, directions, observe)`` the
    observed rows' derivatives ``(m, k)`` along ``directions`` ``(n_physical, k)``
    (``observe``: the sparse observation ``(n_obs 3, n 3)``); ``warm_starts``
    (:class:`WarmStarts`); ``material_density(physical)``: the density written with the
    material and where it comes from, ``None`` where the simulation does not determine it.
    """

    warm_starts: WarmStarts

    def simulate(self, physical: Tensor) -> Tensor:
        ...

    def jacobian(self, physical: Tensor, directions: Tensor, observe: Tensor) -> Tensor:
        ...

    def material_density(self, physical: Tensor) -> tuple[float, str] | None:
        ...


# -- what the other layers ask of a problem ----------------------------------------------------
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
class MotionProblem(Protocol):
    """A problem in motion (``problem.dynamic=true``): frames are output times.

    ``output_times`` ``(K,)`` (s) and ``integrator`` those of its
    :class:`~torchfit.problems.dynamic.TimeIntegration` (its ``time``, whose
    ``report(physical)`` says how the motion is integrated and its estimated error:
    ``result.json``'s ``time_integration``); ``frame_errors(x)`` per output time; ``x_true``
    the noise-free motion ``(K, n_nodes, dim)``; ``simulation_input(theta)`` what
    ``simulate`` takes (``[k..., alpha, beta]``).
    """

    output_times: Tensor
    integrator: Any

    def frame_errors(self, x: Tensor) -> dict[str, Any]:
        ...


@runtime_checkable
class MeshProblem(Protocol):
    """A problem on a simplicial mesh (``mesh.points``, ``mesh.cells``, ``mesh.extent``)."""

    mesh: Any


@runtime_checkable
class BodyProblem(Protocol):
    """A 3-D body fitted to an animation (``arm3d``, ``animation``): what
    :class:`torchfit.reporting.body.BodyOutputs` draws and exports, and what the run asks.

    ``animation`` has ``faces`` ``(T, 3)`` and ``path``; ``observation`` maps tet positions
    ``(F, n, 3)`` to the user's surface vertices (``surface(x)`` ``(F, V, 3)``), gives the
    noise-free target surface (``clean_surface(x_true)``) and the distance of every surface
    vertex to it (``surface_error_field(x, x_true)`` ``(F, V)``); ``report`` summarises a
    field per region (``region_summary(field)``), says how close each frame is to a fold
    (``min_volume_ratio(x)`` ``(F,)``: :func:`torchfit.run.fit_continued` fits the frames far
    from one first) and warns of parameters on the bounds (``bound_warning``);
    ``comparison.simulate_model(model, E)`` simulates the same body with another constitutive
    model; ``with_frames(numbers)`` is the same problem on some of its frames with the same
    targets there; ``frame_numbers()`` the animation's number of every fitted frame.

    What the outputs need besides: ``full_bend_frame``, the reference frame (the most
    deformed one) that pictures and the model comparison show; ``tet_regions``, a region
    label per tetrahedron ``(n_tets,)`` or ``None``; ``writes_animation``, whether the
    problem wrote its animation folder itself (the run directory gets a copy); ``tet``,
    ``tet_options`` and ``grid`` the run keeps with the mesh (``mesh.npz``).
    """

    animation: Any
    mesh: Any
    full_bend_frame: int
    tet_regions: Any
    region_names: list[str]
    observed_vertices: Tensor
    writes_animation: bool
    #: what the joint region's volume change is called (``elbow`` on the arm)
    joint_label: str
    #: the pictures' camera, rows ``right, depth, up`` (unit axes ``(3, 3)``; up: the
    #: file's up axis, else the body's: :func:`~.body.motion.picture_up`), or ``None``
    view_axes: Any
    #: where the documentation explains a fold of this body (``None``: nowhere)
    fold_docs: str | None
    observation: Any
    report: Any
    comparison: Any

    def frame_numbers(self) -> list[int]:
        ...

    def with_frames(self, numbers: list[int]) -> Any:
        ...


@runtime_checkable
class EmbeddedSurfaceProblem(Protocol):
    """A body whose user surface is embedded in its tet mesh: ``embedding.cells`` ``(V,)``
    the tetrahedron of each surface vertex and ``embedding.weights`` ``(V, 4)`` its
    barycentric weights there (what the per-vertex material layer samples the field with)."""

    mesh: Any
    embedding: Any


@runtime_checkable
class PosedProblem(Protocol):
    """A problem whose frames are poses simulated by a :class:`BodySimulation` (a rigged
    body): what a distributed run needs to split them over ranks (where the frames are
    independent: not a :class:`MotionProblem`).

    ``poses``: the body's simulation; the frame-by-frame one
    (:class:`~torchfit.problems.body.poses.FramePoses`) has ``simulated_poses()`` (each
    distinct pose once: an index ``(P,)``, or every frame), ``repeated_poses`` (``(first
    frames (P,), pose of each frame (F,))`` or ``None``), ``pose_jacobian(theta,
    parameterization, observe)`` ``(P, rows, n_params)``, ``plug(simulation, jacobian)``
    (the seam the run plugs its split into) and ``quasistatic`` (the pose simulation in
    use); ``input_digests()`` what every rank must share.
    """

    n_frames: int
    poses: Any

    def input_digests(self) -> dict[str, str]:
        ...
