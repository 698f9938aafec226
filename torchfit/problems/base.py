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

Two collaborators every problem has (:mod:`.protocols`): :attr:`InverseProblem.time`, how its
frames relate in time (independent equilibria by default; a problem in motion builds a
:class:`~torchfit.problems.dynamic.TimeIntegration` in :meth:`~InverseProblem.build_model`,
which appends the damping to the parameters and reports it), and
:attr:`InverseProblem.warm_starts`, what its simulations carry over from one another (none
by default; a Newton solver's :class:`~torchfit.physics.Equilibrium`). The protocols of
:mod:`.protocols` (:class:`~.protocols.FieldImageProblem`, ...) say what the reporting layer
may ask of a problem beyond the template.

Nothing here relies on torch's default dtype: tensors are made in ``problem.dtype``
(``float64`` unless ``problem.dtype=float32``).
"""
from __future__ import annotations

import contextlib
import hashlib
import math
from typing import Any, Callable, ClassVar, ContextManager, Sequence

import numpy as np
import torch
from torch import Tensor

from ..errors import SimulationError
from ..memory import check_allocation
from ..params import Parameterization
from ..residual import ForwardProducts, ResidualFunction
from .config import (ProblemConfig, ProblemConfigError, check_device, dtype_of, make_config,
                     validate_config)
from .dynamic import QUASISTATIC
from .protocols import TimeModel, WarmStarts


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


class NoWarmStarts:
    """:class:`~.protocols.WarmStarts` of simulations that carry nothing over: each depends
    on its input alone (a linear solve, an integration from the initial state)."""

    def independent(self) -> ContextManager[None]:
        return contextlib.nullcontext()

    def warm_start_state(self) -> dict[str, Any]:
        return {}

    def restore_warm_start_state(self, state: dict[str, Any], device: Any = None) -> None:
        """Nothing to restore."""


#: the warm starts of a problem whose simulations carry nothing over (the default)
NO_WARM_STARTS = NoWarmStarts()


def has_forward_jacobian(problem: "InverseProblem") -> bool:
    """Whether ``problem``'s class implements :meth:`~InverseProblem.forward_jacobian` or
    :meth:`~InverseProblem.simulate_jacobian` (the one-pass Jacobian the solvers may use)."""
    cls = type(problem)
    return cls.forward_jacobian is not InverseProblem.forward_jacobian or \
        cls.simulate_jacobian is not InverseProblem.simulate_jacobian


def has_forward_products(problem: "InverseProblem") -> bool:
    """Whether ``problem``'s class implements :meth:`~InverseProblem.forward_products`."""
    return type(problem).forward_products is not InverseProblem.forward_products


# -- the problem ----------------------------------------------------------------------------
class InverseProblem:
    """Base class and template constructor of every problem.

    Subclasses set :attr:`config_class` and implement the hooks :meth:`build_model`,
    :meth:`build_parameterization`, :meth:`build_observation`, :meth:`true_field`,
    :meth:`simulate`, :meth:`observe` (and optionally :meth:`check`,
    :meth:`measured_data`, :meth:`observation_index`). The protocols of
    :mod:`.protocols` (:class:`~.protocols.FieldImageProblem`, ...) are opt-in: the base
    defines none of their members.

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
    #: problems whose parameters mean the same thing share a family (``None``: the name)
    parameter_family: ClassVar[str | None] = None
    #: how the frames relate in time (a problem in motion sets its own in build_model)
    time: TimeModel = QUASISTATIC
    #: what the simulations carry over from one another (a Newton solver's equilibrium)
    warm_starts: WarmStarts = NO_WARM_STARTS
    #: report ``k_err_rel_aligned`` (the error after the best scale) though the data fix
    #: the scale (the body in time: its scale is fixed by inertia, weakly)
    aligned_error: ClassVar[bool] = False
    #: the metrics a problem reports besides the generic ones (its :meth:`metrics` adds
    #: them), listed before the time model's
    extra_metric_names: ClassVar[tuple[str, ...]] = ()

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
        self.parameterization = self.time.parameterization(self.build_parameterization(cfg))
        self.build_observation(cfg)
        self.theta0 = self.initial_parameters(cfg)
        truth = self.true_field(cfg)
        if truth is not None:
            self.field_true = truth.to(device=self.device, dtype=self.dtype)
            with self.warm_starts.independent():   # the truth never seeds the fit's starts
                try:
                    self.x_true = self.simulate(self.time.true_input(self.field_true)).detach()
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
        return self.parameterization.constant(float(getattr(cfg, self.initial_setting)),
                                              self.dtype, self.device)

    def truth_settings(self) -> list[str]:
        """The settings of the synthetic target's true material (``problem.<key>``; the
        time model's scalars after the field's)."""
        return [f"problem.{key}" for key in self.truth_fields] + self.time.truth_settings()

    def unsimulated_truth(self, error: SimulationError) -> ProblemConfigError:
        """The one-line refusal of a synthetic target whose simulation failed with ``error``
        (naming :meth:`truth_settings`)."""
        return ProblemConfigError(
            f"{', '.join(self.truth_settings())}: the synthetic target cannot be simulated "
            f"with this true material ({' '.join(str(error).split())}); choose a material the "
            "simulation can reach")

    def start_settings(self) -> list[str]:
        """The settings of the fit's start (``problem.<key>``, the time model's scalars
        after the field's; ``init=`` comes on top)."""
        return [f"problem.{self.initial_setting}", *self.time.start_settings()]

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
        if not has_forward_jacobian(self):
            raise NotImplementedError(f"{type(self).__name__} has no one-pass Jacobian")
        with torch.no_grad():
            theta = theta.detach()
            field = self.parameterization(theta)
            directions = self.parameterization.jacobian(theta)
            return _observe_columns(self.observe, self.simulate_jacobian(field, directions))

    # -- optional: explicit derivative products (no autograd graph) -------------------
    def forward_products(self, theta: Tensor) -> ForwardProducts:
        """Optional hook: :meth:`forward` at ``theta`` with explicit ``J v`` and ``J^T w``
        (:class:`~torchfit.residual.ForwardProducts`), built from explicit pieces (the
        parameterisation's ``jvp``/``vjp``, :meth:`torchfit.physics.Equilibrium.linearization`,
        the transpose of a gather) instead of the autograd engine. Where implemented,
        :meth:`residual` hands it to the solvers; it must agree with :meth:`forward`'s
        autograd products (each problem's tests compare them)."""
        raise NotImplementedError(f"{type(self).__name__} has no explicit products")

    # -- shared -----------------------------------------------------------------------
    def forward(self, theta: Tensor) -> Tensor:
        """``observe(simulate(map(theta)))``, ``(m,)``."""
        return self.observe(self.simulate(self.parameterization(theta)))

    def residual(self, explicit_products: bool = True) -> ResidualFunction:
        """The residual the solvers get (with :meth:`forward_jacobian` and
        :meth:`forward_products` where implemented; ``explicit_products=False`` keeps the
        autograd products, the reference the explicit ones are checked against)."""
        gauge = self.parameterization.scale_direction if self.scale_free else None
        jacobian = self.forward_jacobian if has_forward_jacobian(self) else None
        products = self.forward_products if explicit_products and has_forward_products(self) \
            else None
        return ResidualFunction(self.forward, self.data, self.noise_level, gauge, jacobian,
                                accuracy=self.time.accuracy(self.simulation_accuracy()),
                                products=products,
                                product_consistency=self.time.product_consistency())

    def theta_bounds(self) -> tuple[Tensor, Tensor] | None:
        """``(lower, upper)`` ``(n_params,)`` bounds on ``theta`` that the solver keeps
        (``torchfit.solvers.bounds``; ``-inf`` / ``inf`` entries: unbounded), or ``None``
        (the default: unbounded)."""
        return None

    def simulation_accuracy(self) -> float | None:
        """Relative accuracy of :meth:`simulate` with independent frames (``None``: machine
        precision); problems solved by Newton to a tolerance say so, for the
        finite-difference check. In time :attr:`time` decides
        (:meth:`~.protocols.TimeModel.accuracy`)."""
        return None

    def field(self, theta: Tensor) -> Tensor:
        """The fitted field at ``theta`` (what metrics, images and ``field.npy`` show; in time
        without the damping)."""
        return self.time.field(self.parameterization(theta.detach()))

    def simulation_input(self, theta: Tensor) -> Tensor:
        """What :meth:`simulate` takes at ``theta`` (no graph): the parameterisation's
        output. It equals :meth:`field` unless the parameterisation also maps scalars
        that are not part of the field (dynamics: ``[k, alpha, beta]``)."""
        return self.parameterization(theta.detach())

    def true_theta(self) -> Tensor:
        """``theta`` of the truth (``parameterization.inverse`` of its simulation input)."""
        assert self.field_true is not None
        return self.parameterization.inverse(self.time.true_input(self.field_true))

    def metric_names(self) -> list[str]:
        """Keys of docs/problems.md's metric table that :meth:`metrics` reports, in its order."""
        names = ["misfit"]
        if self.x_true is not None:
            names += ["u_err_inf", "u_err_2"]
        if self.field_true is not None:
            names += ["k_err_inf", "k_err_2", "k_err_rel"]
            if self.scale_free or self.aligned_error:
                names.append("k_err_rel_aligned")
        return names + list(self.extra_metric_names) + self.time.metric_names()

    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        """The metrics of docs/problems.md at ``theta`` (state errors on every node and frame;
        the time model's after the field's)."""
        with torch.no_grad():
            field = self.field(theta)
            physical = self.simulation_input(theta)
            if x is None:
                x = self.simulate(physical)
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
                if self.scale_free or self.aligned_error:
                    scale = float(torch.dot(field, truth) / torch.dot(field, field))
                    out["k_err_rel_aligned"] = float(
                        torch.linalg.vector_norm(scale * field - truth)) / truth_norm
            out.update(self.time.metrics(physical))
        return out

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

    def describe(self) -> dict[str, object]:
        """Sizes for logs and result files."""
        return {"name": self.name, "n_params": self.parameterization.n_params,
                "n_data": int(self.data.numel()), "noise_level": self.noise_level,
                "scale_free": self.scale_free, **self.time.describe()}


def parameter_meaning(problem: InverseProblem) -> dict[str, object]:
    """What ``problem``'s parameters mean beyond their count, recorded in ``params.pt``:
    ``init=`` refuses a run whose meaning differs even where the counts agree. The problem
    (problems of one family share parameters), the spatial dimension, and whether the
    damping is appended (dynamic)."""
    return {"problem": problem.parameter_family or problem.name, "dim": int(problem.dim),
            "dynamic": bool(getattr(problem.cfg, "dynamic", False))}


def array_digest(*arrays: Any) -> str:
    """A short hash of arrays' shapes, dtypes and bytes (:meth:`InverseProblem.input_digests`)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a.detach().cpu().numpy() if isinstance(a, Tensor) else a)
        h.update(f"{a.dtype.str}{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]
