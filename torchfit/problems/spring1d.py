"""``spring1d``: the hanging mass-spring chain of PROBLEMS.md.

``n`` springs and ``n + 1`` nodes on a vertical line, node 0 fixed at ``x = 0``
(positions measured along gravity). Rest length ``1/n`` and node mass ``1/n``; every
node carries its weight ``g / n`` and the last node an extra end load ``F`` per frame
(load cases ``F in (0, 1, 2)``). Not scale-free: gravity and loads are forces.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch
from torch import Tensor

from ..params import chain_edges, per_element
from ..physics import Equilibrium, SpringChain1D
from .base import (InverseProblem, ProblemConfigError, add_noise, check_finite_targets,
                   node_frame_index, require)

DATA_MODES = ("dense", "sparse")


@dataclasses.dataclass
class Spring1DConfig:
    """Settings of ``problem=spring1d`` (defaults are the canonical values)."""

    name: str = "spring1d"
    n: int = 64                         # number of springs
    gravity: float = 9.81               # m/s^2, downward (the positive axis)
    loads: List[float] = dataclasses.field(default_factory=lambda: [0.0, 1.0, 2.0])  # end load per frame
    fixed_nodes: List[int] = dataclasses.field(default_factory=lambda: [0])  # Dirichlet, held at rest
    data: str = "dense"                 # dense | sparse
    sparse_stride: int = 8              # sparse data observe nodes stride, 2*stride, ...
    noise: float = 0.0                  # sigma of the Gaussian noise on every observed value
    seed: int = 0
    k_background: float = 100.0
    k0: float = 100.0                   # initial guess, constant
    transform: str = "exp"              # exp (k = exp(theta)) | identity
    targets: Optional[str] = None       # .npy of user target positions (frames, n + 1)
    backend: str = "scipy"              # linear solves: scipy | cg
    device: str = "cpu"


def true_stiffness(n: int, background: float = 100.0) -> Tensor:
    """Piecewise-constant truth: ``k = 100``, ``k[16:32] = 400``, ``k[40:48] = 25``.

    The slices are those of PROBLEMS.md for ``n = 64``; for other ``n`` they scale with
    the chain so that the same fractions of it are stiff and soft.
    """
    k = torch.full((n,), float(background), dtype=torch.float64)
    def span(lo: int, hi: int) -> slice:
        return slice(round(lo * n / 64), round(hi * n / 64))
    k[span(16, 32)] = 4.0 * background
    k[span(40, 48)] = 0.25 * background
    return k


class Spring1D(InverseProblem):
    """The hanging chain as an inverse problem (fit per-spring stiffness)."""

    name = "spring1d"
    field_name = "k"
    scale_free = False

    def __init__(self, cfg: Spring1DConfig | None = None, **overrides: object) -> None:
        cfg = dataclasses.replace(cfg or Spring1DConfig(), **overrides)
        self.cfg = cfg
        self._validate(cfg)
        n = cfg.n
        self.device = torch.device(cfg.device)
        dtype = torch.float64
        nodes = torch.arange(n + 1)
        edges = torch.stack([nodes[:-1], nodes[1:]], dim=1)
        loads = torch.as_tensor(cfg.loads, dtype=dtype)
        n_frames = loads.numel()
        weight = torch.full((n + 1,), cfg.gravity / n, dtype=dtype)   # mass 1/n times g
        external = weight.repeat(n_frames, 1)
        external[:, n] += loads
        self.model = SpringChain1D(edges.to(self.device),
                                   torch.full((n,), 1.0 / n, dtype=dtype, device=self.device),
                                   external.to(self.device))
        fixed = torch.as_tensor(sorted(int(i) for i in cfg.fixed_nodes), dtype=torch.long)
        self.equilibrium = Equilibrium(self.model, fixed, backend=cfg.backend)
        # Fixed nodes stay at their rest positions i/n (node 0 at x = 0).
        self.fixed_values = (fixed.to(dtype) / n).repeat(n_frames, 1).to(self.device)
        self.n_frames = n_frames
        self.parameterization = per_element(n, chain_edges(n), cfg.transform, name="stiffness")

        free = [i for i in range(n + 1) if i not in set(fixed.tolist())]
        if cfg.data == "dense":
            self.observed_nodes = torch.as_tensor(free, dtype=torch.long)
        else:
            self.observed_nodes = torch.as_tensor(
                [i for i in range(cfg.sparse_stride, n + 1, cfg.sparse_stride) if i in free],
                dtype=torch.long)
        require(self.observed_nodes.numel() > 0, "no node is observed: lower "
                "problem.sparse_stride or use problem.data=dense")

        self.theta0 = self.parameterization.constant(cfg.k0, dtype, self.device)
        frame_of, node_of = node_frame_index(n_frames, self.observed_nodes, 1)
        if cfg.targets is None:
            self.field_true = true_stiffness(n, cfg.k_background).to(self.device)
            self.x_true = self.simulate(self.field_true).detach()
            clean = self.observe(self.x_true)
        else:
            self.field_true = None
            self.x_true = None
            clean = self._load_targets(cfg.targets, n_frames, n + 1)
            check_finite_targets(clean, frame_of, node_of)
        self.data, self.noise_level = add_noise(clean, cfg.noise, cfg.seed)

    @staticmethod
    def _validate(cfg: Spring1DConfig) -> None:
        require(isinstance(cfg.n, int) and cfg.n >= 1,
                f"problem.n must be an integer >= 1 (number of springs), got {cfg.n!r}")
        require(cfg.data in DATA_MODES,
                f"problem.data={cfg.data!r} is not a data mode; choose one of {DATA_MODES}")
        require(cfg.noise >= 0, f"problem.noise must be >= 0 (a standard deviation), got "
                f"{cfg.noise}")
        require(cfg.sparse_stride >= 1, f"problem.sparse_stride must be >= 1, got "
                f"{cfg.sparse_stride}")
        require(cfg.data != "sparse" or cfg.sparse_stride <= cfg.n, f"problem.sparse_stride={cfg.sparse_stride} is "
                f"larger than the chain (n={cfg.n}): no node would be observed")
        require(len(cfg.loads) >= 1, "problem.loads needs at least one load case (frame)")
        require(all(np.isfinite(float(f)) for f in cfg.loads),
                f"problem.loads must be finite, got {list(cfg.loads)}")
        require(len(cfg.fixed_nodes) >= 1,
                "problem.fixed_nodes is empty: a chain with no Dirichlet node is a singular "
                "system (it can fall freely); fix at least one node, e.g. [0]")
        require(all(0 <= int(i) <= cfg.n for i in cfg.fixed_nodes),
                f"problem.fixed_nodes must lie in 0..{cfg.n}, got {list(cfg.fixed_nodes)}")
        require(cfg.k0 > 0 and cfg.k_background > 0,
                "problem.k0 and problem.k_background must be positive stiffnesses")
        require(np.isfinite(cfg.gravity), "problem.gravity must be finite")

    def _load_targets(self, path: str, n_frames: int, n_nodes: int) -> Tensor:
        file = Path(path)
        require(file.is_file(), f"problem.targets={path!r} does not exist")
        positions = torch.as_tensor(np.load(file), dtype=torch.float64, device=self.device)
        require(positions.shape == (n_frames, n_nodes),
                f"problem.targets must hold positions of shape (frames={n_frames}, "
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
