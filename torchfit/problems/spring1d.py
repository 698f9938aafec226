"""``spring1d``: the hanging mass-spring chain of docs/problems.md.

``n`` springs and ``n + 1`` nodes on a vertical line, node 0 fixed at ``x = 0``
(positions measured along gravity). Rest length ``1/n`` and node mass ``1/n``; every
node carries its weight ``g / n`` and the last node an extra end load ``F`` per frame
(load cases ``F in (0, 1, 2)``). Not scale-free: gravity and loads are forces.

``problem.dynamic=true`` (:class:`DynamicSpring1D`): the chain is released at rest length
(``x_i = i/n``, at rest) at ``t = 0`` under gravity, node masses ``density / n``, Rayleigh
damping ``alpha``, ``beta``; an end load eases (C2) from ``load_values[0]`` to
``load_values[-1]`` between ``load_times``. It falls, oscillates and settles. Targets:
positions at the output times (``data=dense``: every free node; ``sparse``: every
``sparse_stride``-th). Fitted: ``k`` per spring, ``alpha``, ``beta``
(:mod:`torchfit.problems.dynamic`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, ClassVar, List, Optional

import numpy as np

import torch
from torch import Tensor

from ..memory import load_npy
from ..params import Parameterization, chain_edges, per_element
from ..physics import Equilibrium, ScalarSpringNetwork
from ..physics.dynamics import DynamicSystem, KeyedMotion
from .base import InverseProblem
from .config import (DataMode, ProblemConfig, ProblemConfigError, require, require_setting,
                     resolve_backend)
from .dynamic import (DynamicSettings, TimeIntegration, check_dynamic_flag,
                      check_dynamic_settings, time_steps_allocation)



@dataclasses.dataclass
class Spring1DConfig(DynamicSettings, ProblemConfig):
    """Settings of ``problem=spring1d`` (defaults are the canonical values; ``noise``,
    ``seed``, ``transform``, ``backend``, ``device``, ``dtype`` from :class:`ProblemConfig`,
    ``problem.dynamic=true`` and its settings from :class:`DynamicSettings`)."""

    name: str = "spring1d"
    n: int = 64                         # number of springs (n + 1 nodes)
    gravity: float = 9.81               # m/s^2, downward (the positive axis)
    loads: List[float] = dataclasses.field(default_factory=lambda: [0.0, 1.0, 2.0])  # end load per frame
    fixed_nodes: List[int] = dataclasses.field(default_factory=lambda: [0])  # Dirichlet, held at rest
    data: DataMode = DataMode.dense     # dense: every free node | sparse: every sparse_stride-th
    sparse_stride: int = 8              # sparse data observe nodes stride, 2*stride, ...
    k_background: float = 100.0
    k0: float = 100.0                   # initial guess, constant
    targets: Optional[str] = None       # .npy of user target positions (frames, n + 1)
    # -- problem.dynamic=true: the end load eases from load_values[0] to load_values[-1] --
    load_times: List[float] = dataclasses.field(default_factory=lambda: [0.5, 1.0])   # s
    load_values: List[float] = dataclasses.field(default_factory=lambda: [0.0, 2.0])  # end load


def true_stiffness(n: int, background: float = 100.0,
                   dtype: torch.dtype = torch.float64) -> Tensor:
    """Piecewise-constant truth: ``k = 100``, ``k[16:32] = 400``, ``k[40:48] = 25``.

    The slices are those of docs/problems.md for ``n = 64``; for other ``n`` they scale with
    the chain so that the same fractions of it are stiff and soft.
    """
    k = torch.full((n,), float(background), dtype=dtype)
    def span(lo: int, hi: int) -> slice:
        return slice(round(lo * n / 64), round(hi * n / 64))
    k[span(16, 32)] = 4.0 * background
    k[span(40, 48)] = 0.25 * background
    return k


class Spring1D(InverseProblem):
    """The hanging chain as an inverse problem (fit per-spring stiffness)."""

    config_class = Spring1DConfig
    name = "spring1d"
    field_name = "k"
    scale_free = False
    initial_setting = "k0"
    truth_fields = ("k_background",)
    dim = 1
    #: the chain in motion is another class (:class:`DynamicSpring1D`)
    in_time: ClassVar[bool] = False

    def check(self, cfg: Spring1DConfig) -> None:
        check_dynamic_flag(self, cfg, self.in_time)
        require_setting(isinstance(cfg.n, int) and cfg.n >= 1, cfg, "n",
                        "must be an integer >= 1 (number of springs)")
        require_setting(cfg.sparse_stride >= 1, cfg, "sparse_stride", "must be >= 1")
        require_setting(cfg.data != DataMode.sparse or cfg.sparse_stride <= cfg.n, cfg,
                        "sparse_stride", f"is larger than the chain (n={cfg.n}): no node "
                        "would be observed; use a stride <= n")
        require_setting(len(cfg.loads) >= 1, cfg, "loads",
                        "needs at least one load case (frame)")
        require_setting(len(cfg.fixed_nodes) >= 1, cfg, "fixed_nodes",
                        "is empty: a chain with no Dirichlet node is a singular system (it "
                        "can fall freely); fix at least one node, e.g. [0]")
        require_setting(all(0 <= int(i) <= cfg.n for i in cfg.fixed_nodes), cfg,
                        "fixed_nodes", f"must lie in 0..{cfg.n}")
        for key in ("k0", "k_background"):
            require_setting(getattr(cfg, key) > 0, cfg, key, "must be a positive stiffness")

    def allocation(self, cfg: Spring1DConfig) -> list[tuple[Any, ...]]:
        # per node and frame: load, position, adjoint, two work vectors; per node: the
        # stiffness, its gradient and the sparse factor (about 16 values)
        frames = len(cfg.loads)
        return [(f"problem.n={cfg.n}", (cfg.n + 1) * (5 * frames + 16) * 8.0,
                 f"{cfg.n + 1} nodes x {frames} frames")]

    # -- the hooks of the template --------------------------------------------------------
    def build_model(self, cfg: Spring1DConfig) -> None:
        n, dtype, device = cfg.n, self.dtype, self.device
        nodes = torch.arange(n + 1)
        edges = torch.stack([nodes[:-1], nodes[1:]], dim=1)
        loads = torch.as_tensor(cfg.loads, dtype=dtype)
        n_frames = loads.numel()
        weight = torch.full((n + 1,), cfg.gravity / n, dtype=dtype)   # mass 1/n times g
        external = weight.repeat(n_frames, 1)
        external[:, n] += loads
        self.model = ScalarSpringNetwork(edges.to(device),
                                   torch.full((n,), 1.0 / n, dtype=dtype, device=device),
                                   external.to(device))
        self.fixed = torch.as_tensor(sorted(int(i) for i in cfg.fixed_nodes), dtype=torch.long)
        self.equilibrium = Equilibrium(self.model, self.fixed,
                                       backend=resolve_backend(cfg.backend, self.device, 1))
        # Fixed nodes stay at their rest positions i/n (node 0 at x = 0).
        self.fixed_values = (self.fixed.to(dtype) / n).repeat(n_frames, 1).to(device)
        self.n_frames = n_frames

    def build_parameterization(self, cfg: Spring1DConfig) -> Parameterization:
        return per_element(cfg.n, chain_edges(cfg.n), cfg.transform.value, name="stiffness",
                           dtype=self.dtype)

    def build_observation(self, cfg: Spring1DConfig) -> None:
        n = cfg.n
        fixed = set(self.fixed.tolist())
        free = [i for i in range(n + 1) if i not in fixed]
        if cfg.data == DataMode.dense:
            self.observed_nodes = torch.as_tensor(free, dtype=torch.long)
        else:
            self.observed_nodes = torch.as_tensor(
                [i for i in range(cfg.sparse_stride, n + 1, cfg.sparse_stride) if i in free],
                dtype=torch.long)
        require(self.observed_nodes.numel() > 0, f"problem.sparse_stride={cfg.sparse_stride}: "
                "no free node is observed; lower problem.sparse_stride or use problem.data=dense")

    def true_field(self, cfg: Spring1DConfig) -> Tensor | None:
        if cfg.targets is not None:
            return None
        return true_stiffness(cfg.n, cfg.k_background, self.dtype)

    def measured_data(self, cfg: Spring1DConfig) -> Tensor:
        """Observed user positions from ``problem.targets`` (``.npy``, ``(frames, n + 1)``)."""
        n_frames, n_nodes = self.n_frames, cfg.n + 1
        file = Path(cfg.targets)
        require(file.is_file(), f"problem.targets={cfg.targets}: the file does not exist")
        positions = torch.as_tensor(load_npy(file, f"problem.targets={cfg.targets}",
                                             ProblemConfigError),
                                    dtype=self.dtype, device=self.device)
        require(positions.shape == (n_frames, n_nodes),
                f"problem.targets={cfg.targets}: must hold positions of shape (frames={n_frames}, "
                f"nodes={n_nodes}), got {tuple(positions.shape)}")
        return self.observe(positions[..., None])

    # -- the forward model ------------------------------------------------------------
    def simulate(self, stiffness: Tensor) -> Tensor:
        """Node positions ``(F, n + 1, 1)`` (length units, along gravity) for stiffness ``(n,)``."""
        if stiffness.shape != (self.cfg.n,):
            raise ProblemConfigError(f"stiffness must have shape ({self.cfg.n},) (one per "
                                     f"spring), got {tuple(stiffness.shape)}")
        return self.equilibrium(stiffness, self.fixed_values)[..., None]

    def observe(self, x: Tensor) -> Tensor:
        """Observed node positions, flattened frame-major ``(F * n_observed,)``."""
        return x[:, self.observed_nodes.to(x.device), :].reshape(-1)


class DynamicSpring1D(Spring1D):
    """The chain in motion (``problem.dynamic=true``; module docstring): fit ``k`` per
    spring with ``alpha`` and ``beta`` to node positions at the output times (its
    :attr:`time` a :class:`~torchfit.problems.dynamic.TimeIntegration`)."""

    in_time = True
    time: TimeIntegration

    def check(self, cfg: Spring1DConfig) -> None:
        super().check(cfg)
        check_dynamic_settings(cfg)
        require_setting(cfg.targets is None, cfg, "targets", "user targets are static frames; "
                        "a dynamic chain is fitted to its simulated motion (problem.targets=null)")
        require_setting(len(cfg.load_times) == len(cfg.load_values) >= 1, cfg, "load_values",
                        f"needs one end load per key time (problem.load_times has "
                        f"{len(cfg.load_times)})")
        times = list(cfg.load_times)
        require_setting(all(b > a for a, b in zip(times[:-1], times[1:])), cfg, "load_times",
                        "must increase strictly (s)")

    def allocation(self, cfg: Spring1DConfig) -> list[tuple[Any, ...]]:
        frames = len(cfg.output_times) if cfg.output_times else cfg.frames
        outputs = "problem.output_times" if cfg.output_times else f"problem.frames={frames}"
        return [(f"problem.n={cfg.n} x {outputs}", (cfg.n + 1) * (5 * frames + 16) * 8.0,
                 f"{cfg.n + 1} nodes x {frames} output times"),
                *time_steps_allocation(cfg, cfg.n + 1)]

    def build_model(self, cfg: Spring1DConfig) -> None:
        n, dtype, device = cfg.n, self.dtype, self.device
        nodes = torch.arange(n + 1)
        edges = torch.stack([nodes[:-1], nodes[1:]], dim=1)
        self.model = ScalarSpringNetwork(edges.to(device),
                                   torch.full((n,), 1.0 / n, dtype=dtype, device=device),
                                   torch.zeros(1, n + 1, dtype=dtype, device=device))
        self.fixed = torch.as_tensor(sorted(int(i) for i in cfg.fixed_nodes), dtype=torch.long)
        rest = torch.arange(n + 1, dtype=dtype, device=device) / n
        end_load = torch.zeros(len(cfg.load_values), n + 1, dtype=dtype, device=device)
        end_load[:, n] = torch.as_tensor(cfg.load_values, dtype=dtype)
        self.system = DynamicSystem(
            self.model, n, torch.full((n + 1,), cfg.density / n, dtype=dtype, device=device),
            self.fixed, KeyedMotion(torch.zeros(1), rest[self.fixed][None]),
            KeyedMotion(torch.as_tensor(cfg.load_times, dtype=dtype), end_load),
            torch.full((n + 1,), cfg.gravity, dtype=dtype, device=device), rest, vertex_dim=1)
        self.time = TimeIntegration.from_settings(cfg, self.system, 1,
                                                  resolve_backend(cfg.backend, self.device, 1),
                                                  start_field=float(cfg.k0))
        self.output_times, self.integrator = self.time.output_times, self.time.integrator
        self.n_frames = int(self.output_times.numel())

    def simulate(self, physical: Tensor) -> Tensor:
        """Node positions ``(K, n + 1, 1)`` at the output times for ``[k (n,), alpha, beta]``."""
        return self.time.positions(physical)

    def simulate_jacobian(self, physical: Tensor, directions: Tensor) -> Tensor:
        """``(d positions / d [k, alpha, beta]) directions`` ``(K, n + 1, 1, k)``."""
        return self.time.jacobian(physical, directions)

    def frame_errors(self, x: Tensor) -> dict[str, np.ndarray]:
        """Position errors per output time against the noise-free truth."""
        return self.time.frame_errors(x, self.x_true)

    def frame_names(self) -> list[str]:
        return self.time.frame_names()

    @property
    def default_sheet_frame(self) -> int:
        return self.n_frames // 2
