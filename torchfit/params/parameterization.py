"""Parameterisations: the map from the optimisation vector ``theta`` to a physical field.

``field = B @ transform(theta)`` where ``B`` is a fixed non-negative linear basis
(identity for one value per element, a 0/1 label matrix for one value per region,
interpolation weights for a coarse grid) and ``transform`` is ``exp`` (positivity,
the default) or the identity. Each parameterisation also exposes

* the TV difference operator ``D`` (``(n_edges, n_params)``, one row ``e_j - e_i`` per
  pair of neighbouring parameters), which the Split Bregman solver uses without knowing
  where it comes from, and optionally the grouping of its rows for isotropic TV
  (:meth:`Parameterization.difference_groups`: the axis differences of one grid cell
  form one group, see :func:`grid_groups`);
* the scale (gauge) direction: the direction in ``theta`` along which the field is
  multiplied by a constant (``ones`` for ``exp``, ``theta`` itself for the identity).
  Scale-free problems hand it to the solvers so that they do not drift along it.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

_TRANSFORMS = ("exp", "identity")


class Parameterization:
    """``field = basis @ transform(theta)``.

    Args:
        n_params: length of ``theta``.
        edges: ``(n_edges, 2)`` pairs of neighbouring parameters (for ``D``); may be
            empty (no TV possible then).
        basis: ``(n_field, n_params)`` sparse or dense non-negative matrix, or ``None``
            for the identity (one parameter per field value).
        transform: ``'exp'`` (positive field, the default) or ``'identity'``.
        name: what the field is, for messages and logs (e.g. ``'stiffness'``).
        groups: ``(n_edges,)`` group index of every edge for isotropic TV (the
            differences along each axis from one grid cell), or ``None`` (no grouping:
            isotropic and anisotropic TV coincide).
        dtype: floating-point type of what the parameterisation makes itself (``D``,
            :meth:`constant` by default); never torch's default dtype.
    """

    def __init__(self, n_params: int, edges: Tensor | np.ndarray | None = None,
                 basis: Tensor | None = None, transform: str = "exp",
                 name: str = "field", groups: Tensor | np.ndarray | None = None,
                 dtype: torch.dtype = torch.float64) -> None:
        if n_params < 1:
            raise ValueError(f"a parameterisation needs at least one parameter, got {n_params}")
        if transform not in _TRANSFORMS:
            raise ValueError(f"unknown transform {transform!r}; choose one of {_TRANSFORMS}")
        self.n_params = int(n_params)
        self.dtype = dtype
        self.transform = str(transform)
        self.name = name
        self.basis = basis
        self.n_field = self.n_params if basis is None else int(basis.shape[0])
        if basis is not None and basis.shape[1] != n_params:
            raise ValueError(f"basis has {basis.shape[1]} columns for {n_params} parameters")
        edges_t = torch.as_tensor(np.asarray(edges if edges is not None else np.zeros((0, 2))),
                                  dtype=torch.long).reshape(-1, 2)
        if edges_t.numel() and (edges_t.min() < 0 or edges_t.max() >= n_params):
            raise ValueError("parameter adjacency refers to a parameter out of range")
        self.edges = edges_t
        if groups is not None:
            groups_t = torch.as_tensor(np.asarray(groups), dtype=torch.long).reshape(-1)
            if groups_t.numel() != edges_t.shape[0]:
                raise ValueError(f"groups must give one group index per edge ({edges_t.shape[0]}), "
                                 f"got {groups_t.numel()}")
            if groups_t.numel() and groups_t.min() < 0:
                raise ValueError("groups must be >= 0")
            self.groups: Tensor | None = groups_t
        else:
            self.groups = None

    # -- the map ----------------------------------------------------------------------
    def __call__(self, theta: Tensor) -> Tensor:
        """Field ``(n_field,)`` from ``theta`` ``(n_params,)`` (differentiable)."""
        self.check(theta)
        return self._apply_basis(torch.exp(theta) if self.transform == "exp" else theta)

    def _apply_basis(self, values: Tensor) -> Tensor:
        """``basis @ values`` ``(n_field,)`` (differentiable, forward mode included)."""
        if self.basis is None:
            return values
        if self.basis.layout != torch.strided:
            # a gather and a scatter-add instead of a sparse product: torch's sparse matmul
            # has no forward-mode derivative (J v of the solvers)
            rows, cols, weights = self._sparse_entries(values)
            return values.new_zeros(self.n_field).index_add(0, rows, weights * values[cols])
        return self.basis.to(values) @ values

    def _sparse_entries(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Rows, columns and values of the sparse basis on ``like``'s device/dtype (cached)."""
        key = (like.dtype, like.device)
        if getattr(self, "_entries_key", None) != key:
            coo = self.basis.to_sparse_coo().coalesce()
            rows, cols = coo.indices()
            self._entries = (rows.to(like.device), cols.to(like.device),
                             coo.values().to(like))
            self._entries_key = key
        return self._entries

    def jacobian(self, theta: Tensor) -> Tensor:
        """``d field / d theta`` as a dense ``(n_field, n_params)`` matrix at ``theta``.

        ``basis * exp(theta)`` (columns scaled) for ``exp``, ``basis`` for the identity
        (the identity basis is ``I``). Dense on purpose: it is meant for problems with
        few parameters (the solvers' dense-Jacobian path); no autograd graph.
        """
        self.check(theta)
        theta = theta.detach()
        if self.basis is None:
            dense = torch.eye(self.n_params, dtype=theta.dtype, device=theta.device)
        else:
            basis = self.basis.to_dense() if self.basis.layout != torch.strided else self.basis
            dense = basis.to(dtype=theta.dtype, device=theta.device)
        if self.transform == "exp":
            return dense * torch.exp(theta)[None, :]
        return dense.clone()

    def _transform_derivative(self, theta: Tensor) -> Tensor | None:
        """Diagonal of ``d transform / d theta`` ``(n_params,)``, ``None`` for the identity."""
        return torch.exp(theta.detach()) if self.transform == "exp" else None

    def jvp(self, theta: Tensor, v: Tensor) -> Tensor:
        """``(d field / d theta) v`` ``(n_field,)`` for ``v`` ``(n_params,)``, explicit (no
        autograd): the transform's diagonal, then the basis."""
        scale = self._transform_derivative(theta)
        return self._apply_basis(v if scale is None else scale * v)

    def vjp(self, theta: Tensor, w: Tensor) -> Tensor:
        """``(d field / d theta)^T w`` ``(n_params,)`` for ``w`` ``(n_field,)``, explicit."""
        if self.basis is None:
            values = w
        elif self.basis.layout != torch.strided:
            rows, cols, weights = self._sparse_entries(w)
            values = w.new_zeros(self.n_params).index_add_(0, cols, weights * w[rows])
        else:
            values = self.basis.to(w).T @ w
        scale = self._transform_derivative(theta)
        return values if scale is None else scale * values

    def inverse(self, field: Tensor) -> Tensor:
        """``theta`` whose image is ``field`` (basis must be the identity or one-hot)."""
        if self.basis is not None:
            # Least-squares pre-image of the basis, then the inverse transform.
            dense = self.basis.to_dense() if self.basis.is_sparse else self.basis
            values = torch.linalg.lstsq(dense.to(field), field.reshape(-1, 1)).solution.reshape(-1)
        else:
            values = field
        if self.transform == "exp":
            if not bool((values > 0).all()):
                raise ValueError(f"the {self.name} must be positive under the exp "
                                 "parameterisation")
            return torch.log(values)
        return values.clone()

    def constant(self, value: float, dtype: torch.dtype | None = None,
                 device: torch.device | str = "cpu") -> Tensor:
        """``theta`` of a constant field ``value`` (in ``dtype``, by default :attr:`dtype`)."""
        dtype = self.dtype if dtype is None else dtype
        if self.transform == "exp":
            if not value > 0:
                raise ValueError(f"the {self.name} must be positive, got {value}")
            return torch.full((self.n_params,), math.log(value), dtype=dtype, device=device)
        return torch.full((self.n_params,), float(value), dtype=dtype, device=device)

    def check(self, theta: Tensor) -> None:
        if theta.shape != (self.n_params,):
            raise ValueError(f"parameter vector for the {self.name} must have shape "
                             f"({self.n_params},), got {tuple(theta.shape)}")

    # -- what the solvers may use -----------------------------------------------------
    def difference_operator(self) -> Tensor:
        """``D``: sparse ``(n_edges, n_params)`` with rows ``e_j - e_i`` for edges ``(i, j)``."""
        n_edges = self.edges.shape[0]
        if n_edges == 0:
            raise ValueError(f"the {self.name} parameterisation has no neighbouring "
                             "parameters, so it has no difference operator (TV needs at "
                             "least two adjacent parameters)")
        rows = torch.arange(n_edges).repeat_interleave(2)
        cols = self.edges.reshape(-1)
        vals = torch.tensor([-1.0, 1.0], dtype=self.dtype).repeat(n_edges)
        return torch.sparse_coo_tensor(torch.stack([rows, cols]), vals,
                                       (n_edges, self.n_params),
                                       check_invariants=False).coalesce()

    def difference_groups(self) -> Tensor | None:
        """Group index ``(n_edges,)`` of every row of :meth:`difference_operator` for
        isotropic TV (``None`` when the parameterisation has no such grouping)."""
        return None if self.groups is None else self.groups.clone()

    def scale_direction(self, theta: Tensor) -> Tensor:
        """Unit direction in ``theta`` that multiplies the whole field by a constant."""
        direction = torch.ones_like(theta) if self.transform == "exp" else theta.detach().clone()
        return direction / torch.linalg.vector_norm(direction)


def chain_edges(n: int) -> np.ndarray:
    """Neighbours ``(i, i + 1)`` of a chain of ``n`` cells, ``(n - 1, 2)``."""
    idx = np.arange(n - 1)
    return np.stack([idx, idx + 1], axis=1)


def grid_edges(shape: tuple[int, ...]) -> np.ndarray:
    """Axis neighbours of a regular grid of cells (row-major numbering), ``(n_edges, 2)``."""
    index = np.arange(int(np.prod(shape))).reshape(shape)
    pairs = []
    for axis in range(len(shape)):
        lo = np.take(index, np.arange(shape[axis] - 1), axis=axis).reshape(-1)
        hi = np.take(index, np.arange(1, shape[axis]), axis=axis).reshape(-1)
        pairs.append(np.stack([lo, hi], axis=1))
    return np.concatenate(pairs, axis=0) if pairs else np.zeros((0, 2), dtype=np.int64)


def grid_groups(shape: tuple[int, ...]) -> np.ndarray:
    """Isotropic-TV groups of :func:`grid_edges` (same edge order), ``(n_edges,)``.

    Every edge ``(lo, hi)`` of ``grid_edges(shape)`` is the forward difference along one
    axis from cell ``lo``; grouping by ``lo`` puts the x-, y- (and z-) differences of one
    cell together, so that ``sum_g ||(D theta)_g||`` is the usual isotropic TV with
    forward differences (cells on the far boundary have fewer components: Neumann).
    """
    return grid_edges(shape)[:, 0].copy()


def per_element(n_cells: int, cell_edges: np.ndarray | None = None, transform: str = "exp",
                name: str = "field", groups: np.ndarray | None = None,
                dtype: torch.dtype = torch.float64) -> Parameterization:
    """One parameter per element (cell, spring, triangle, tetrahedron).

    ``groups`` (one per edge) groups the rows of ``D`` for isotropic TV, e.g.
    :func:`grid_groups` for ``cell_edges = grid_edges(shape)``.
    """
    return Parameterization(n_cells, cell_edges, None, transform, name, groups, dtype)


def per_grid_cell(shape: tuple[int, ...], transform: str = "exp",
                  name: str = "field", dtype: torch.dtype = torch.float64) -> Parameterization:
    """One parameter per cell of a regular grid (row-major), with its isotropic-TV groups."""
    return Parameterization(int(np.prod(shape)), grid_edges(shape), None, transform, name,
                            grid_groups(shape), dtype)


def per_region(labels: Tensor | np.ndarray, cell_edges: np.ndarray | None = None,
               transform: str = "exp", name: str = "field",
               dtype: torch.dtype = torch.float64) -> Parameterization:
    """One parameter per region of a label map (``labels[c]`` in ``0..n_regions-1``).

    Two regions are neighbours when some pair of neighbouring cells carries their labels.
    """
    labels_np = np.asarray(torch.as_tensor(labels).cpu(), dtype=np.int64).reshape(-1)
    n_regions = int(labels_np.max()) + 1 if labels_np.size else 0
    used = np.unique(labels_np)
    if labels_np.size == 0 or labels_np.min() < 0 or used.size != n_regions:
        raise ValueError("region labels must be 0..n_regions-1 with every region used")
    basis = torch.sparse_coo_tensor(
        torch.from_numpy(np.stack([np.arange(labels_np.size), labels_np])),
        torch.ones(labels_np.size, dtype=dtype), (labels_np.size, n_regions),
        check_invariants=False).coalesce()
    region_edges = np.zeros((0, 2), dtype=np.int64)
    if cell_edges is not None and len(cell_edges):
        pairs = labels_np[np.asarray(cell_edges)]
        pairs = np.sort(pairs[pairs[:, 0] != pairs[:, 1]], axis=1)
        region_edges = np.unique(pairs, axis=0) if len(pairs) else region_edges
    return Parameterization(n_regions, region_edges, basis, transform, name, dtype=dtype)


def _grid_box(shape: tuple[int, ...], lower, upper) -> tuple[tuple[int, ...], np.ndarray,
                                                              np.ndarray]:
    """Checked ``(shape, lower, upper)`` of a node grid spanning a box."""
    shape = tuple(int(s) for s in shape)
    lo = np.asarray(lower, dtype=np.float64).reshape(-1)
    hi = np.asarray(upper, dtype=np.float64).reshape(-1)
    if len(shape) not in (2, 3) or lo.shape != (len(shape),) or hi.shape != (len(shape),):
        raise ValueError(f"a node grid needs a 2-D or 3-D shape with lower and upper corners "
                         f"of the same length, got shape {shape}, lower {lo.tolist()}, "
                         f"upper {hi.tolist()}")
    if min(shape) < 2:
        raise ValueError(f"a node grid needs at least 2 nodes per axis, got shape {shape}")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
        raise ValueError(f"the grid's box must be finite with upper > lower on every axis, "
                         f"got lower {lo.tolist()}, upper {hi.tolist()}")
    return shape, lo, hi


def grid_node_positions(shape: tuple[int, int, int], lower, upper) -> np.ndarray:
    """Positions ``(nx * ny * nz, 3)`` of the nodes of a regular grid spanning the box
    ``[lower, upper]`` (corners included), row-major: node ``(ix, iy, iz)`` is row
    ``(ix * ny + iy) * nz + iz`` (also for 2-D shapes, ``(nx * ny, 2)``)."""
    shape, lo, hi = _grid_box(shape, lower, upper)
    axes = [lo[a] + (hi[a] - lo[a]) * np.arange(n) / (n - 1) for a, n in enumerate(shape)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.reshape(-1) for g in mesh], axis=1)


def per_grid_node(shape: tuple[int, int, int], points: np.ndarray, lower, upper,
                  transform: str = "exp", name: str = "field",
                  dtype: torch.dtype = torch.float64) -> Parameterization:
    """One parameter per node of a regular grid over a box, interpolated (trilinearly) to
    ``points`` (e.g. the centroids of a tetrahedral mesh's cells).

    Args:
        shape: ``(nx, ny, nz)`` nodes per axis, each at least 2 (``(nx, ny)`` works too:
            bilinear).
        points: ``(n, 3)`` where the field is wanted; points outside the box are clamped
            onto it.
        lower, upper: ``(3,)`` corners of the box (same unit as ``points``), ``upper >
            lower``.

    Returns:
        A :class:`Parameterization` with ``nx * ny * nz`` parameters (numbered as in
        :func:`grid_node_positions`), the sparse COO (coalesced) basis ``(n, nx * ny * nz)``
        of trilinear weights (each row sums to 1, at most 8 nonzeros), the TV edges
        :func:`grid_edges` between neighbouring nodes and their isotropic groups
        :func:`grid_groups`.
    """
    shape, lo, hi = _grid_box(shape, lower, upper)
    d = len(shape)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != d or len(p) == 0:
        raise ValueError(f"points for a {d}-D node grid must be a non-empty (n, {d}) array, "
                         f"got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("points for the node grid must be finite")
    dims = np.array(shape)
    t = np.clip((p - lo) / (hi - lo), 0.0, 1.0) * (dims - 1)       # grid coordinates
    base = np.minimum(np.floor(t).astype(np.int64), dims - 2)      # lower node of the cell
    frac = t - base                                                 # in [0, 1]
    rows, cols, vals = [], [], []
    for corner in range(2 ** d):                                    # 4 or 8 corners
        bits = np.array([(corner >> (d - 1 - a)) & 1 for a in range(d)])
        weight = np.prod(np.where(bits == 1, frac, 1.0 - frac), axis=1)
        node = np.ravel_multi_index(tuple((base + bits).T), shape)
        keep = weight != 0
        rows.append(np.nonzero(keep)[0])
        cols.append(node[keep])
        vals.append(weight[keep])
    n_nodes = int(np.prod(shape))
    basis = torch.sparse_coo_tensor(
        torch.from_numpy(np.stack([np.concatenate(rows), np.concatenate(cols)])),
        torch.from_numpy(np.concatenate(vals)).to(dtype), (len(p), n_nodes),
        check_invariants=False).coalesce()
    return Parameterization(n_nodes, grid_edges(shape), basis, transform, name,
                            grid_groups(shape), dtype)


class FieldAndScalars(Parameterization):
    """A field parameterisation followed by a few named scalars (``[k..., alpha, beta]``).

    ``theta = [theta_field (n_field_params,), theta_scalars (n_scalars,)]`` maps to the
    physical vector ``[field(theta_field) (n_field,), transform(theta_scalars)]``: the
    field by its own parameterisation, each scalar by this parameterisation's transform
    (``exp``: positive; ``identity``: as is). The solvers see one vector and one residual.

    * ``D`` (TV) has the field's rows and zero columns for the scalars: TV never penalises
      them; isotropic groups are the field's.
    * :meth:`constant` sets the field to a constant and the scalars to their
      ``initial`` values.
    * ``scale_direction`` is the field's (scalars held): the direction that multiplies the
      field by a constant.

    Args:
        field: the field's :class:`Parameterization`.
        names: the scalars' names (``('alpha', 'beta')``).
        initial: their values for :meth:`constant`.
        transform: ``'exp'`` or ``'identity'`` for the scalars.
    """

    def __init__(self, field: Parameterization, names: tuple[str, ...] | list[str],
                 initial: tuple[float, ...] | list[float], transform: str = "exp") -> None:
        names = tuple(str(n) for n in names)
        if len(names) != len(initial) or not names:
            raise ValueError(f"give one initial value per scalar: names {names}, "
                             f"initial {list(initial)}")
        super().__init__(field.n_params + len(names), field.edges.numpy(), None, transform,
                         f"{field.name} and {', '.join(names)}", field.groups, field.dtype)
        self.field_parameterization = field
        self.scalar_names = names
        self.scalar_initial = tuple(float(v) for v in initial)
        self.n_scalars = len(names)
        self.n_field = field.n_field + self.n_scalars

    @property
    def n_field_params(self) -> int:
        return self.field_parameterization.n_params

    def _scalars(self, theta_scalars: Tensor) -> Tensor:
        return torch.exp(theta_scalars) if self.transform == "exp" else theta_scalars

    def __call__(self, theta: Tensor) -> Tensor:
        """``[field (n_field - n_scalars,), scalars (n_scalars,)]`` (differentiable)."""
        self.check(theta)
        m = self.n_field_params
        return torch.cat([self.field_parameterization(theta[:m]), self._scalars(theta[m:])])

    def split(self, physical: Tensor) -> tuple[Tensor, Tensor]:
        """``(field, scalars)`` of a physical vector."""
        k = self.field_parameterization.n_field
        return physical[:k], physical[k:]

    def jacobian(self, theta: Tensor) -> Tensor:
        """Block-diagonal ``d physical / d theta`` ``(n_field, n_params)``."""
        self.check(theta)
        m = self.n_field_params
        field = self.field_parameterization.jacobian(theta[:m])
        theta_s = theta.detach()[m:]
        scalars = torch.diag(torch.exp(theta_s) if self.transform == "exp"
                             else torch.ones_like(theta_s))
        return torch.block_diag(field.to(theta), scalars.to(theta))

    def jvp(self, theta: Tensor, v: Tensor) -> Tensor:
        """``(d physical / d theta) v`` ``(n_field,)``: the field's, then the scalars'."""
        m = self.n_field_params
        scalars = v[m:] if self.transform != "exp" else torch.exp(theta.detach()[m:]) * v[m:]
        return torch.cat([self.field_parameterization.jvp(theta[:m], v[:m]), scalars])

    def vjp(self, theta: Tensor, w: Tensor) -> Tensor:
        """``(d physical / d theta)^T w`` ``(n_params,)``."""
        m, k = self.n_field_params, self.field_parameterization.n_field
        scalars = w[k:] if self.transform != "exp" else torch.exp(theta.detach()[m:]) * w[k:]
        return torch.cat([self.field_parameterization.vjp(theta[:m], w[:k]), scalars])

    def inverse(self, physical: Tensor) -> Tensor:
        """``theta`` of a physical vector ``[field, scalars]``."""
        field, scalars = self.split(physical)
        if self.transform == "exp":
            if not bool((scalars > 0).all()):
                raise ValueError(f"{', '.join(self.scalar_names)} must be positive under the exp "
                                 "parameterisation")
            theta_s = torch.log(scalars)
        else:
            theta_s = scalars.clone()
        return torch.cat([self.field_parameterization.inverse(field), theta_s])

    def constant(self, value: float, dtype: torch.dtype | None = None,
                 device: torch.device | str = "cpu") -> Tensor:
        """``theta`` of the constant field ``value`` with the scalars at their initial values."""
        dtype = self.dtype if dtype is None else dtype
        field = self.field_parameterization.constant(value, dtype, device)
        scalars = torch.tensor(self.scalar_initial, dtype=dtype, device=device)
        if self.transform == "exp":
            if not bool((scalars > 0).all()):
                raise ValueError(f"{', '.join(self.scalar_names)} must be positive under the exp "
                                 f"parameterisation, got {list(self.scalar_initial)}")
            scalars = torch.log(scalars)
        return torch.cat([field, scalars])

    def scale_direction(self, theta: Tensor) -> Tensor:
        m = self.n_field_params
        direction = torch.zeros_like(theta)
        direction[:m] = self.field_parameterization.scale_direction(theta[:m])
        return direction
