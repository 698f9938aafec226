"""``poisson2d``: the seed's stretched square, ``div(k grad x) = 0`` by finite differences.

Rest square ``[0, s]^2`` with ``N x N`` nodes and one stiffness per cell. For each
position component the 5-point scheme ``sum_q k_pq (x_q - x_p) = 0`` holds at every
non-Dirichlet node, ``k_pq`` being the mean of the (one or two) cells touching edge
``pq``; left and right columns are Dirichlet with ``x = X / s``, top and bottom are
free (zero flux). The scheme is the weighted graph Laplacian of the grid edges, i.e. a
network of zero-rest-length scalar springs, so the physics is
:class:`~torchfit.physics.ScalarSpringNetwork` with edge weights ``k_pq``. The two components are two right-hand sides of the same matrix
``A(k)``: they are solved as two "frames" of one linear equilibrium, sharing one
factorisation.

Scale-free: ``x(a k) = x(k)``; metrics report ``k_err_rel_aligned`` and the solvers get
the constant direction of ``log k`` as the gauge, so they never move along it.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import Tensor

from ..linalg import coo_to_csr
from ..params import Parameterization, grid_edges, grid_groups, per_element
from ..physics import Equilibrium, ScalarSpringNetwork
from ..residual import ForwardProducts
from ..settings import Choice
from .base import InverseProblem, node_frame_index
from .config import (Backend, DataMode, ProblemConfig, ProblemConfigError, require,
                     require_setting, resolve_backend)


class Pattern(Choice):
    """The true field of poisson2d (docs/problems.md)."""

    blocks = "blocks"
    ipam = "ipam"




@dataclasses.dataclass
class Poisson2DConfig(ProblemConfig):
    """Settings of ``problem=poisson2d`` (defaults are the canonical values; ``noise``,
    ``seed``, ``transform``, ``backend``, ``device``, ``dtype`` from :class:`ProblemConfig`)."""

    name: str = "poisson2d"
    N: int = 64                      # nodes per side; (N - 1)^2 cells, one k each
    s: float = 0.5                   # side of the rest square (stretched onto the unit square)
    pattern: Pattern = Pattern.blocks    # the truth: blocks | ipam
    # dense: every non-Dirichlet node | sparse: nodes (i, j) on the sparse_stride lattice
    data: DataMode = DataMode.dense
    sparse_stride: int = 4           # sparse: nodes (i, j) with i, j multiples of the stride
    k0: float = 1.0                  # initial guess, constant (scale-free: aligned errors)
    # The free stiffness is SPD (a graph Laplacian with positive k and Dirichlet columns):
    # ldl, sparse L D L^T with the ordering kept per pattern (docs/notes/ldl.md); scipy
    # (SuperLU) | banded | cg (torch, CPU or CUDA) as for every problem.
    backend: Backend = Backend.ldl


def blocks_field(centres: np.ndarray) -> np.ndarray:
    """The ``blocks`` truth at cell centres normalised to the unit square."""
    cx, cy = centres[:, 0], centres[:, 1]
    k = np.ones(len(centres))
    k[(cx >= 0.20) & (cx <= 0.45) & (cy >= 0.20) & (cy <= 0.80)] = 5.0
    k[(cx >= 0.60) & (cx <= 0.85) & (cy >= 0.30) & (cy <= 0.60)] = 0.25
    return k


def ipam_field(centres: np.ndarray) -> np.ndarray:
    """The ``ipam`` truth: ``5`` on the ink of the word IPAM, ``1`` elsewhere."""
    from .font import ipam_mask

    return np.where(ipam_mask(centres), 5.0, 1.0)


class Poisson2D(InverseProblem):
    """Fit per-cell ``k`` from the positions of the stretched square."""

    config_class = Poisson2DConfig
    name = "poisson2d"
    field_name = "k"
    scale_free = True
    initial_setting = "k0"
    dim = 2

    def check(self, cfg: Poisson2DConfig) -> None:
        require_setting(isinstance(cfg.N, int) and cfg.N >= 3, cfg, "N",
                        "must be an integer >= 3 (nodes per side)")
        require_setting(cfg.s > 0, cfg, "s", "must be positive (side of the rest square)")
        require_setting(cfg.sparse_stride >= 1, cfg, "sparse_stride", "must be >= 1")
        require_setting(cfg.data != DataMode.sparse or cfg.sparse_stride < cfg.N - 1, cfg,
                        "sparse_stride", f"is larger than the grid (N={cfg.N}): no interior "
                        "column would be observed; use a stride < N - 1")
        require_setting(cfg.k0 > 0, cfg, "k0", "must be a positive stiffness")

    def allocation(self, cfg: Poisson2DConfig) -> list[tuple[str, float, str]]:
        # per node: two components of position, load, adjoint and work vectors, the index
        # grids, the edges and the sparse factor (about 40 values, a lower bound)
        return [(f"problem.N={cfg.N}", cfg.N * cfg.N * 40 * 8.0,
                 f"{cfg.N} x {cfg.N} = {cfg.N * cfg.N:.3g} grid nodes")]

    # -- the hooks of the template --------------------------------------------------------
    def build_model(self, cfg: Poisson2DConfig) -> None:
        N, s, dtype, device = cfg.N, cfg.s, self.dtype, self.device
        # Node (i, j) at (i h, j h), numbered i * N + j; cell (ci, cj) numbered ci * (N-1) + cj.
        h = s / (N - 1)
        self._ii, self._jj = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
        self.rest_positions = torch.from_numpy(
            np.stack([self._ii.ravel() * h, self._jj.ravel() * h], axis=1)).to(dtype)
        ci, cj = np.meshgrid(np.arange(N - 1), np.arange(N - 1), indexing="ij")
        self._centres = np.stack([(ci.ravel() + 0.5) * h, (cj.ravel() + 0.5) * h], axis=1)
        self.cell_centres = torch.from_numpy(self._centres).to(dtype)
        edges, edge_cells = self._edge_cells(N)
        self.edge_cells = torch.from_numpy(edge_cells).to(device)   # (n_edges, 2)
        n_nodes = N * N
        self.model = ScalarSpringNetwork(torch.from_numpy(edges).to(device),
                                   torch.zeros(len(edges), dtype=dtype, device=device),
                                   torch.zeros(2, n_nodes, dtype=dtype, device=device))
        self.dirichlet_nodes = np.concatenate([np.arange(N), np.arange((N - 1) * N, N * N)])
        fixed = torch.from_numpy(np.sort(self.dirichlet_nodes))
        self.equilibrium = Equilibrium(self.model, fixed,
                                       backend=resolve_backend(cfg.backend, self.device, 2))
        # Dirichlet: x = X / s on the left and right columns, per component ("frame").
        self.fixed_values = (self.rest_positions[fixed].T / s).contiguous().to(device)

    def build_parameterization(self, cfg: Poisson2DConfig) -> Parameterization:
        n = cfg.N - 1
        return per_element(n ** 2, grid_edges((n, n)), cfg.transform.value, name="stiffness",
                           groups=grid_groups((n, n)), dtype=self.dtype)

    def build_observation(self, cfg: Poisson2DConfig) -> None:
        is_free = np.ones(cfg.N * cfg.N, dtype=bool)
        is_free[self.dirichlet_nodes] = False
        if cfg.data == DataMode.dense:
            observed = np.nonzero(is_free)[0]
        else:
            stride = cfg.sparse_stride
            on_lattice = (self._ii.ravel() % stride == 0) & (self._jj.ravel() % stride == 0)
            observed = np.nonzero(is_free & on_lattice)[0]
        require(observed.size > 0, f"problem.sparse_stride={cfg.sparse_stride}: no "
                "non-Dirichlet node is observed; lower it")
        self.observed_nodes = torch.from_numpy(observed)
        self.frame_of, self.node_of = node_frame_index(1, self.observed_nodes, 2)

    def observation_index(self) -> tuple[Tensor, Tensor]:
        return self.frame_of, self.node_of

    def true_field(self, cfg: Poisson2DConfig) -> Tensor:
        normalised = self._centres / cfg.s           # float64 whatever problem.dtype is
        truth = blocks_field(normalised) if cfg.pattern == Pattern.blocks else ipam_field(normalised)
        return torch.from_numpy(truth).to(self.dtype)

    @staticmethod
    def _edge_cells(N: int) -> tuple[np.ndarray, np.ndarray]:
        """Grid edges ``(n_edges, 2)`` (node pairs) and the two cells touching each.

        An edge on the top or bottom boundary touches one cell, listed twice, so that
        ``k_pq = (k[c0] + k[c1]) / 2`` is the mean of the cells touching it in every case.
        """
        node = np.arange(N * N).reshape(N, N)
        cell = np.arange((N - 1) ** 2).reshape(N - 1, N - 1)
        # Edges along x ((i, j) - (i+1, j)): cells (i, j-1) and (i, j), clipped at the border.
        i, j = (a.ravel() for a in np.meshgrid(np.arange(N - 1), np.arange(N), indexing="ij"))
        along_x = np.stack([node[i, j], node[i + 1, j]], axis=1)
        cells_x = np.stack([cell[i, np.clip(j - 1, 0, N - 2)], cell[i, np.clip(j, 0, N - 2)]], axis=1)
        # Edges along y ((i, j) - (i, j+1)): cells (i-1, j) and (i, j), clipped at the border.
        i, j = (a.ravel() for a in np.meshgrid(np.arange(N), np.arange(N - 1), indexing="ij"))
        along_y = np.stack([node[i, j], node[i, j + 1]], axis=1)
        cells_y = np.stack([cell[np.clip(i - 1, 0, N - 2), j], cell[np.clip(i, 0, N - 2), j]], axis=1)
        return np.concatenate([along_x, along_y]), np.concatenate([cells_x, cells_y])

    # -- the forward model ------------------------------------------------------------
    def simulate(self, stiffness: Tensor) -> Tensor:
        """Node positions ``(1, N*N, 2)`` of the stretched square for per-cell ``k``."""
        n_cells = (self.cfg.N - 1) ** 2
        if stiffness.shape != (n_cells,):
            raise ProblemConfigError(f"stiffness must have shape ({n_cells},) (one per cell), "
                                     f"got {tuple(stiffness.shape)}")
        # The mean as index_select + lerp: under forward-mode AD (the solvers' J v)
        # advanced indexing and products with a Python scalar fall back to Python
        # decompositions of the ops, ~10x slower than these two kernels.
        weights = torch.lerp(stiffness.index_select(0, self.edge_cells[:, 0]),
                             stiffness.index_select(0, self.edge_cells[:, 1]), 0.5)
        components = self.equilibrium(weights, self.fixed_values)      # (2, N*N)
        return components.T[None]

    def forward_products(self, theta: Tensor) -> ForwardProducts:
        """:meth:`forward` at ``theta`` with explicit ``J v`` and ``J^T w``: the exp map's
        diagonal, the edge mean ``W`` (sparse, built once) and its transpose, the
        equilibrium's free-dof products (one solve with the stored factor, both
        components as two right-hand sides) and the gather of the observed nodes' rows and
        its transpose. No autograd graph."""
        theta = theta.detach()
        stiffness = self.parameterization(theta)
        first, second = self.edge_cells[:, 0], self.edge_cells[:, 1]
        weights = torch.lerp(stiffness.index_select(0, first), stiffness.index_select(0, second), 0.5)
        state = self.equilibrium.linearization(weights, self.fixed_values)     # (2, N*N)
        edge_mean, edge_mean_t, rows = self._explicit_operators(stiffness)
        n_free = self.equilibrium.free_dofs.numel()

        def jvp(v: Tensor) -> Tensor:
            dw = edge_mean @ self.parameterization.jvp(theta, v)
            return state.free_jvp(dw).view(-1).index_select(0, rows)

        def vjp(w: Tensor) -> Tensor:
            grad = w.new_zeros(2 * n_free).index_copy_(0, rows, w).view(n_free, 2)
            return self.parameterization.vjp(theta, edge_mean_t @ state.free_vjp(grad))

        return ForwardProducts(state.x.index_select(1, self.observed_nodes.to(state.x.device))
                               .T.reshape(-1), jvp, vjp)

    def _explicit_operators(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The edge mean ``W`` ``(n_edges, n_cells)`` and ``W^T`` as CSR, and the positions
        of the observed values in the free-dof block ``(n_free, 2)`` flattened (node-major,
        both components: the data's order), built once per device and dtype."""
        key = (like.device, like.dtype)
        if getattr(self, "_explicit_key", None) != key:
            n_edges, n_cells = self.edge_cells.shape[0], (self.cfg.N - 1) ** 2
            edges = torch.arange(n_edges, device=like.device).repeat(2)
            cells = self.edge_cells.T.reshape(-1).to(like.device)
            half = torch.full((2 * n_edges,), 0.5, dtype=like.dtype, device=like.device)
            node_rows = self.equilibrium.free_position(self.observed_nodes)
            rows = (2 * node_rows[:, None] + torch.arange(2)).reshape(-1).to(like.device)
            self._explicit = (coo_to_csr(edges, cells, half, (n_edges, n_cells)),
                              coo_to_csr(cells, edges, half, (n_cells, n_edges)), rows)
            self._explicit_key = key
        return self._explicit

    def observe(self, x: Tensor) -> Tensor:
        """Both components of the observed nodes, ``(2 * n_observed,)``."""
        return x.index_select(1, self.observed_nodes.to(x.device)).reshape(-1)

    def field_image(self, field: Tensor) -> np.ndarray:
        """The per-cell field as an ``(N-1, N-1)`` image, row 0 at the top (y up)."""
        n = self.cfg.N - 1
        return field.detach().cpu().numpy().reshape(n, n).T[::-1]
