"""The template every canonical problem follows: ``y = observe(simulate(map(theta)))``.

A problem owns the mesh, the true field, the data (with seeded noise), the
observation and the metrics of docs/problems.md. It contains no solver logic: solvers get
:meth:`InverseProblem.residual`, nothing else. Its settings are a
:class:`~torchfit.problems.config.ProblemConfig`.

:class:`InverseProblem.__init__` is a template: config -> generic checks ->
:meth:`~InverseProblem.check` (the problem's own) -> device and dtype ->
:meth:`~InverseProblem.build_model` (mesh, physics) ->
:meth:`~InverseProblem.build_parameterization` ->
:meth:`~InverseProblem.build_observation` -> ``theta0`` ->
:meth:`~InverseProblem.true_field` -> ``x_true = simulate(truth)`` -> ``observe`` (or
:meth:`~InverseProblem.measured_data` for user targets) -> finite-target check ->
seeded noise -> ``data``. A new problem writes its physics and its data, nothing else.
The protocols (:class:`FieldImageProblem`, ...) say what the reporting layer may ask of a
problem beyond the template.

Nothing here relies on torch's default dtype: tensors are made in ``problem.dtype``
(``float64`` unless ``problem.dtype=float32``).
"""
from __future__ import annotations

import contextlib
import hashlib
import math
from typing import (Any, Callable, ClassVar, ContextManager, Protocol, Sequence,
                    runtime_checkable)

import numpy as np
import torch
from torch import Tensor

from ..errors import SimulationError
from ..memory import check_allocation
from ..params import Parameterization
from ..residual import ForwardProducts, ResidualFunction
from .config import (ProblemConfig, ProblemConfigError, check_device, dtype_of, make_config,
                     validate_config)


# -- data helpers -----------------------------------------------------------------------
def _check_finite_targets(targets: Tensor, frame_of: Tensor, node_of: Tensor,
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


def _add_noise(clean: Tensor, sigma: float, seed: int) -> tuple[Tensor, float | None]:
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


def _observe_columns(observe: Callable[[Tensor], Tensor], states: Tensor) -> Tensor:
    """A linear ``observe`` applied to every column of ``states`` ``(..., k)``: ``(m, k)``.

    Vectorised with ``torch.func.vmap(observe, in_dims=-1, out_dims=-1)`` (``observe``
    sees one state of its usual shape, e.g. ``(F, n_nodes, dim)``); an ``observe`` that
    vmap cannot trace falls back to one call per column. ``observe`` must be linear (it
    maps state derivatives): a gather, barycentric weights, a sparse matrix.
    """
    try:
        return torch.func.vmap(observe, in_dims=-1, out_dims=-1)(states)
    except (RuntimeError, NotImplementedError, ValueError, TypeError):
        return torch.stack([observe(states[..., j]) for j in range(states.shape[-1])], dim=-1)


def node_frame_index(n_frames: int, nodes: Sequence[int] | Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """Frame and node of every entry of ``x[:, nodes, :].reshape(-1)``."""
    nodes_t = torch.as_tensor(nodes, dtype=torch.long).cpu()
    frame = torch.arange(n_frames).repeat_interleave(nodes_t.numel() * dim)
    node = nodes_t.repeat_interleave(dim).repeat(n_frames)
    return frame, node


# -- hooks the reporting layer looks for --------------------------------------------------
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
    """A dynamic problem (``problem.dynamic=true``): frames are output times.

    ``output_times`` ``(K,)`` (s); ``frame_errors(x)`` per output time; ``x_true`` the
    noise-free motion ``(K, n_nodes, dim)``; ``simulation_input(theta)`` what
    ``simulate`` takes (``[k..., alpha, beta]``); ``time_integration(theta)`` how the motion
    is integrated and its estimated error (``result.json``'s ``time_integration``).
    """

    output_times: Tensor
    integrator: Any

    def frame_errors(self, x: Tensor) -> dict[str, Any]:
        ...

    def time_integration(self, theta: Tensor) -> dict[str, Any]:
        ...


@runtime_checkable
class MeshProblem(Protocol):
    """A problem on a simplicial mesh (``mesh.points``, ``mesh.cells``, ``mesh.extent``)."""

    mesh: Any


@runtime_checkable
class BodyProblem(Protocol):
    """A 3-D body fitted to an animation (``arm3d``, ``animation``): what
    :class:`torchfit.reporting.body.BodyOutputs` draws and exports.

    ``animation`` has ``faces`` ``(T, 3)`` and ``path``; ``surface(x)`` maps tet positions
    ``(F, n, 3)`` to the user's surface vertices ``(F, V, 3)``; ``clean_surface()`` is the
    noise-free target surface ``(F, V, 3)`` and ``surface_error_field(x)`` the distance of
    every surface vertex to it ``(F, V)``; ``simulate_model(model, E)`` simulates the same
    body with another constitutive model; ``region_summary(field)`` summarises a field per
    region; ``with_frames(numbers)`` is the same problem on some of its frames with the same
    targets there, and ``min_volume_ratio(x)`` ``(F,)`` how close each frame is to a fold
    (:func:`torchfit.run.fit_continued` fits the frames far from one first).

    What the outputs need besides: ``full_bend_frame``, the reference frame (the most
    deformed one) that pictures and the model comparison show; ``tet_regions``, a region
    label per tetrahedron ``(n_tets,)`` or ``None``; ``writes_animation``, whether the
    problem wrote its animation folder itself (the run directory gets a copy).
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

    def surface(self, x: Tensor) -> Tensor:
        ...

    def clean_surface(self) -> Tensor:
        ...

    def surface_error_field(self, x: Tensor) -> Tensor:
        ...

    def independent_simulation(self) -> ContextManager[None]:
        ...

    def frame_numbers(self) -> list[int]:
        ...

    def with_frames(self, numbers: list[int]) -> Any:
        ...

    def min_volume_ratio(self, x: Tensor) -> Any:
        ...

    def simulate_model(self, model: str, E: Tensor, frames: Any = None) -> Tensor:
        ...

    def region_summary(self, field: Tensor) -> dict[str, Any]:
        ...

    def keep_mesh(self, run_dir: Any) -> Any:
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
    """A problem whose frames are independent poses (a quasistatic rigged body): what a
    distributed run needs to split them over ranks.

    ``simulated_poses()`` the frames simulated (each distinct pose once: an index ``(P,)``,
    or every frame); ``repeated_poses`` ``(first frames (P,), pose of each frame (F,))`` or
    ``None``; ``pose_jacobian(theta)`` ``(P, rows, n_params)`` of the simulated poses;
    ``plug(simulation, jacobian)`` the seam the run plugs its split into (the problem's
    pose simulation, and where its ``forward_jacobian`` comes from); ``quasistatic`` the
    pose simulation in use; ``input_digests()`` what every rank must share.
    """

    n_frames: int
    repeated_poses: Any
    quasistatic: Any

    def simulated_poses(self) -> Any:
        ...

    def pose_jacobian(self, theta: Tensor) -> Tensor:
        ...

    def plug(self, simulation: Any, jacobian: Any = None) -> None:
        ...

    def input_digests(self) -> dict[str, str]:
        ...


# -- the problem ----------------------------------------------------------------------------
class InverseProblem:
    """Base class and template constructor of every problem.

    Subclasses set :attr:`config_class` and implement the hooks :meth:`build_model`,
    :meth:`build_parameterization`, :meth:`build_observation`, :meth:`true_field`,
    :meth:`simulate`, :meth:`observe` (and optionally :meth:`check`,
    :meth:`measured_data`, :meth:`observation_index`). The protocols above
    (:class:`FieldImageProblem`, ...) are opt-in: the base defines none of their members.

    Attributes (set by the template):
        cfg: the validated config.
        device, dtype: where and in which precision every tensor lives.
        parameterization: ``theta -> field``.
        theta0: ``(n_params,)`` initial guess (the constant field ``cfg.<initial_setting>``).
        field_true: true field ``(n_field,)`` or ``None`` (user data).
        x_true: noise-free state of the true field, ``(F, n_nodes, dim)`` or ``None``.
        data: ``(m,)`` targets ``y_t``.
        noise_level: ``delta`` or ``None``.
        scale_free: data never fix the global scale of the field.
    """

    config_class: ClassVar[type[ProblemConfig]] = ProblemConfig
    name: str = "problem"
    field_name: str = "k"
    scale_free: bool = False
    #: the config field holding the constant initial guess of the field
    initial_setting: ClassVar[str] = "k0"
    #: the config fields of the synthetic target's true material (named where its
    #: simulation fails)
    truth_fields: ClassVar[tuple[str, ...]] = ()
    #: components per node of the state (``x`` is ``(F, n_nodes, dim)``)
    dim: ClassVar[int] = 1

    cfg: Any
    device: torch.device
    dtype: torch.dtype
    parameterization: Parameterization
    theta0: Tensor
    field_true: Tensor | None
    x_true: Tensor | None
    data: Tensor
    noise_level: float | None

    def __init__(self, cfg: Any = None, **overrides: Any) -> None:
        cfg = make_config(self.config_class, cfg, overrides)
        validate_config(cfg)
        self.check(cfg)
        for setting, nbytes, what, *advice in self.allocation(cfg):   # before any allocation
            check_allocation(setting, nbytes, what, ProblemConfigError, *advice)
        self.cfg = cfg
        self.device = check_device("device", cfg.device)
        self.dtype = dtype_of(cfg.dtype)
        self.build_model(cfg)
        self.parameterization = self.build_parameterization(cfg)
        self.build_observation(cfg)
        self.theta0 = self.initial_parameters(cfg)
        truth = self.true_field(cfg)
        if truth is not None:
            self.field_true = truth.to(device=self.device, dtype=self.dtype)
            with self.independent_simulation():    # the truth never seeds the fit's starts
                try:
                    self.x_true = self.simulate(self.true_simulation_input()).detach()
                except SimulationError as error:
                    raise self.unsimulated_truth(error) from None
            clean, what = self.observe(self.x_true), "simulated target"
        else:
            self.field_true = None
            self.x_true = None
            clean, what = self.measured_data(cfg), "target"
        frame_of, node_of = self.observation_index()
        _check_finite_targets(clean, frame_of, node_of, what)
        self.data, self.noise_level = _add_noise(clean, cfg.noise, cfg.seed)

    # -- hooks: what a problem is --------------------------------------------------------
    def check(self, cfg: Any) -> None:
        """The problem's own checks of ``cfg`` (after the generic ones); raise
        :class:`ProblemConfigError` via :func:`require_setting`."""

    def allocation(self, cfg: Any) -> list[tuple[Any, ...]]:
        """What the settings will allocate, known from ``cfg`` alone: ``(setting, bytes,
        what)`` per size setting (or ``(setting, bytes, what, advice)``: what to change, where
        "choose a smaller value" is wrong) (a lower bound: the solver's work arrays come on top); each
        is refused when it exceeds :func:`torchfit.memory.memory_limit`. Sizes known only
        from files (a mesh, an animation) are checked where they are read."""
        return []

    def build_model(self, cfg: Any) -> None:
        """Mesh and physics (the simulator), on ``self.device`` in ``self.dtype``."""
        raise NotImplementedError

    def build_parameterization(self, cfg: Any) -> Parameterization:
        """The map ``theta -> field``."""
        raise NotImplementedError

    def build_observation(self, cfg: Any) -> None:
        """What is observed (``self.observed_nodes`` for :meth:`observation_index`)."""
        raise NotImplementedError

    def initial_parameters(self, cfg: Any) -> Tensor:
        """``theta0``: the constant field :meth:`initial_value` (a problem may start from a
        field of its own, e.g. a painted material layer)."""
        return self.parameterization.constant(self.initial_value(cfg), self.dtype, self.device)

    def truth_settings(self) -> list[str]:
        """The settings of the synthetic target's true material (``problem.<key>``)."""
        return [f"problem.{key}" for key in self.truth_fields]

    def unsimulated_truth(self, error: SimulationError) -> ProblemConfigError:
        """The one-line refusal of a synthetic target whose simulation failed with ``error``
        (naming :meth:`truth_settings`)."""
        return ProblemConfigError(
            f"{', '.join(self.truth_settings())}: the synthetic target cannot be simulated "
            f"with this true material ({' '.join(str(error).split())}); choose a material the "
            "simulation can reach")

    def start_settings(self) -> list[str]:
        """The settings of the fit's start (``problem.<key>``; ``init=`` comes on top)."""
        return [f"problem.{self.initial_setting}"]

    def initial_value(self, cfg: Any) -> float:
        """The constant field ``theta0`` stands for (``cfg.<initial_setting>``)."""
        return float(getattr(cfg, self.initial_setting))

    def true_field(self, cfg: Any) -> Tensor | None:
        """The true field ``(n_field,)``, or ``None`` when the data are the user's."""
        raise NotImplementedError

    def measured_data(self, cfg: Any) -> Tensor:
        """Observed user targets ``(m,)`` (only when :meth:`true_field` is ``None``)."""
        raise NotImplementedError

    def observation_index(self) -> tuple[Tensor, Tensor]:
        """Frame and node of every observed value, ``(m,)`` each (for messages)."""
        return node_frame_index(int(getattr(self, "n_frames", 1)), self.observed_nodes,
                                self.dim)

    def simulate(self, field: Tensor) -> Tensor:
        """All node positions of all frames, ``(F, n_nodes, dim)``."""
        raise NotImplementedError

    def observe(self, x: Tensor) -> Tensor:
        """Linear sampling of the state: ``(F, n_nodes, dim) -> (m,)``."""
        raise NotImplementedError

    # -- optional: the whole Jacobian in one pass (problems with few parameters) ---------
    def simulate_jacobian(self, field: Tensor, directions: Tensor) -> Tensor:
        """Optional hook: ``(d simulate / d field) directions``, ``(F, n_nodes, dim, k)`` for
        ``directions`` ``(n_field, k)`` (e.g. ``QuasistaticElasticity.jacobian``: one solve
        with ``k`` right-hand sides per frame). Implementing it gives the problem
        :meth:`forward_jacobian`."""
        raise NotImplementedError

    def forward_jacobian(self, theta: Tensor) -> Tensor:
        """Optional hook: ``d forward / d theta``, dense ``(m, n_params)``.

        The default chains the parameterisation's :meth:`~torchfit.params.Parameterization.jacobian`,
        :meth:`simulate_jacobian` and :meth:`observe` applied to every column
        (:func:`_observe_columns`); a problem implements :meth:`simulate_jacobian` (or this
        method). Only then does :meth:`residual` hand it to the solvers, which use it when
        ``n_params`` is small (``solver.dense_jacobian_max_params``).
        """
        if not self.has_forward_jacobian():
            raise NotImplementedError(f"{type(self).__name__} has no one-pass Jacobian")
        with torch.no_grad():
            theta = theta.detach()
            field = self.parameterization(theta)
            directions = self.parameterization.jacobian(theta)
            return _observe_columns(self.observe, self.simulate_jacobian(field, directions))

    def has_forward_jacobian(self) -> bool:
        """Whether the subclass implements :meth:`forward_jacobian` or :meth:`simulate_jacobian`."""
        cls = type(self)
        return cls.forward_jacobian is not InverseProblem.forward_jacobian or \
            cls.simulate_jacobian is not InverseProblem.simulate_jacobian

    # -- optional: explicit derivative products (no autograd graph) -------------------
    def forward_products(self, theta: Tensor) -> ForwardProducts:
        """Optional hook: :meth:`forward` at ``theta`` with explicit ``J v`` and ``J^T w``
        (:class:`~torchfit.residual.ForwardProducts`), built from explicit pieces (the
        parameterisation's ``jvp``/``vjp``, :meth:`torchfit.physics.Equilibrium.linearization`,
        the transpose of a gather) instead of the autograd engine. Where implemented,
        :meth:`residual` hands it to the solvers; it must agree with :meth:`forward`'s
        autograd products (each problem's tests compare them)."""
        raise NotImplementedError(f"{type(self).__name__} has no explicit products")

    def has_forward_products(self) -> bool:
        """Whether the subclass implements :meth:`forward_products`."""
        return type(self).forward_products is not InverseProblem.forward_products

    # -- shared -----------------------------------------------------------------------
    def forward(self, theta: Tensor) -> Tensor:
        """``observe(simulate(map(theta)))``, ``(m,)``."""
        return self.observe(self.simulate(self.parameterization(theta)))

    def residual(self, explicit_products: bool = True) -> ResidualFunction:
        """The residual the solvers get (with :meth:`forward_jacobian` and
        :meth:`forward_products` where implemented; ``explicit_products=False`` keeps the
        autograd products, the reference the explicit ones are checked against)."""
        gauge = self.parameterization.scale_direction if self.scale_free else None
        jacobian = self.forward_jacobian if self.has_forward_jacobian() else None
        products = self.forward_products if explicit_products and self.has_forward_products() \
            else None
        return ResidualFunction(self.forward, self.data, self.noise_level, gauge, jacobian,
                                accuracy=self.simulation_accuracy(), products=products,
                                product_consistency=self.product_consistency())

    def theta_bounds(self) -> tuple[Tensor, Tensor] | None:
        """``(lower, upper)`` ``(n_params,)`` bounds on ``theta`` that the solver keeps
        (``torchfit.solvers.bounds``; ``-inf`` / ``inf`` entries: unbounded), or ``None``
        (the default: unbounded)."""
        return None

    def product_consistency(self) -> float | None:
        """Relative agreement of the simulation's ``J^T w`` with its ``J v`` when they are
        two approximations (each accurate to a solver tolerance), ``None`` (the default)
        when the reverse product is the exact transpose of the forward one (to round-off);
        the dot-product check's bound follows it."""
        return None

    def simulation_accuracy(self) -> float | None:
        """Relative accuracy of :meth:`simulate` (``None``: machine precision); problems
        solved by Newton to a tolerance say so, for the finite-difference check."""
        return None

    def field(self, theta: Tensor) -> Tensor:
        """The fitted field at ``theta`` (what metrics, images and ``field.npy`` show)."""
        return self.parameterization(theta.detach())

    def simulation_input(self, theta: Tensor) -> Tensor:
        """What :meth:`simulate` takes at ``theta`` (no graph): the parameterisation's
        output. It equals :meth:`field` unless the parameterisation also maps scalars
        that are not part of the field (dynamics: ``[k, alpha, beta]``)."""
        return self.parameterization(theta.detach())

    def true_simulation_input(self) -> Tensor:
        """:meth:`simulation_input` of the truth (the true field by default)."""
        assert self.field_true is not None
        return self.field_true

    def true_theta(self) -> Tensor:
        """``theta`` of the truth (``parameterization.inverse`` of its simulation input)."""
        return self.parameterization.inverse(self.true_simulation_input())

    def metric_names(self) -> list[str]:
        """Keys of docs/problems.md's metric table that :meth:`metrics` reports, in its order."""
        names = ["misfit"]
        if self.x_true is not None:
            names += ["u_err_inf", "u_err_2"]
        if self.field_true is not None:
            names += ["k_err_inf", "k_err_2", "k_err_rel"]
            if self.scale_free:
                names.append("k_err_rel_aligned")
        return names

    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        """The metrics of docs/problems.md at ``theta`` (state errors on every node and frame)."""
        with torch.no_grad():
            field = self.field(theta)
            if x is None:
                x = self.simulate(self.simulation_input(theta))
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

    def independent_simulation(self) -> ContextManager[None]:
        """A context whose simulations start cold and seed no later warm start: the
        synthetic target, baselines of reports. A problem whose simulation warm-starts
        from earlier solutions overrides it (where a frame has several equilibria, a
        warm start from the truth's would put the fit on the truth's branch). Default:
        nothing to isolate."""
        return contextlib.nullcontext()

    def simulation_state(self) -> dict[str, Any]:
        """What the next simulations depend on besides their input, as tensors (a run's
        checkpoint keeps it): a problem whose simulations warm-start from earlier solutions
        returns those (:meth:`Equilibrium.warm_start_state`). Default: ``{}``, every
        simulation depends on its input alone."""
        return {}

    def restore_simulation_state(self, state: dict[str, Any]) -> None:
        """Put back what :meth:`simulation_state` returned (in another process, for a resume):
        the next simulations then start exactly where they did there. Default: nothing to
        restore."""

    def bound_warning(self, at_lower: int, at_upper: int) -> str | None:
        """One line to warn with where many of the fitted parameters ended on the bounds
        of :meth:`theta_bounds` (``at_lower``, ``at_upper`` of them), naming the setting
        that moves them; ``None`` (the default: nothing to say)."""
        return None

    def validation_problem(self) -> "InverseProblem | None":
        """The same problem on the frames held out of its fit, simulated for validation at
        every recorded iteration (:mod:`torchfit.run.validation`); built on each call.
        Default: ``None``, nothing held out."""
        return None

    def input_digests(self) -> dict[str, str]:
        """Digests of the input data the problem was built from beyond its settings (a tet
        mesh from a cache, an animation read from files), by name: a checkpoint records
        them, and a resume on other data is refused naming what changed. Default: none
        (the settings determine everything)."""
        return {}

    def parameter_meaning(self) -> dict[str, object]:
        """What the parameters mean beyond their count, recorded in ``params.pt``: ``init=``
        refuses a run whose meaning differs even where the counts agree. The problem
        (problems of one family share parameters), the spatial dimension, and whether the
        damping is appended (dynamic)."""
        return {"problem": self.parameter_family, "dim": int(self.dim),
                "dynamic": bool(getattr(self.cfg, "dynamic", False))}

    #: problems whose parameters mean the same thing share a family (default: the name)
    @property
    def parameter_family(self) -> str:
        return self.name

    def describe(self) -> dict[str, object]:
        """Sizes for logs and result files."""
        return {"name": self.name, "n_params": self.parameterization.n_params,
                "n_data": int(self.data.numel()), "noise_level": self.noise_level,
                "scale_free": self.scale_free}


def array_digest(*arrays: Any) -> str:
    """A short hash of arrays' shapes, dtypes and bytes (:meth:`InverseProblem.input_digests`)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a.detach().cpu().numpy() if isinstance(a, Tensor) else a)
        h.update(f"{a.dtype.str}{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]
