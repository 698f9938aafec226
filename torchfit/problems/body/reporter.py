"""The rigged body's report collaborator: its shape per frame, its regions and bounds, its baseline.

A :class:`BodyReport` is built once per body (after its parameterisation) from the mesh, the
joint region, the region labels and the modulus settings; it answers what the metrics,
pictures, continuation and result files ask of a body beyond its fit:

- per frame ``(F,)`` of tetrahedron positions ``x`` ``(F, n, 3)``: the joint region's
  relative volume change, the inverted tetrahedra, the smallest volume ratio (a fold);
- a field ``(n_tets,)`` per region, with the tetrahedra and parameters on the modulus bounds;
- the line a fit warns with when many parameters end on a bound;
- the homogeneous material's mean surface error (the baseline of ``surface_err_reduction``),
  computed once, on first use, by the ``baseline`` callable the body gives.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
from torch import Tensor

from .bounds import bounds_warning, modulus_bounds, region_report
from .config import RiggedBodyConfig
from .report import inverted_counts, min_volume_ratios, volume_change


class BodyReport:
    """What the run reports of a body's shape and material.

    Args:
        mesh: the tetrahedral mesh (``points``, ``cells``, ``signed_volumes()``).
        joint_cells: the tetrahedra of the joint region ``(k,)``.
        regions: a region label per tetrahedron ``(n_tets,)`` or ``None``; ``region_names``
            their names.
        basis: the field parameterisation's basis (``None``: one parameter per tetrahedron).
        n_params: the fit's parameters (the bounds warning's count).
        cfg: the body's settings (the modulus bounds).
        baseline: the homogeneous material's mean surface error (m), called once.
    """

    def __init__(self, mesh: Any, joint_cells: np.ndarray, regions: np.ndarray | None,
                 region_names: list[str], basis: Tensor | None, n_params: int,
                 cfg: RiggedBodyConfig, baseline: Callable[[], float]) -> None:
        self.mesh, self.joint_cells = mesh, joint_cells
        self.regions, self.region_names = regions, region_names
        self.basis, self.n_params, self.cfg = basis, int(n_params), cfg
        self._baseline = baseline
        self._homogeneous: float | None = None

    def joint_volume_change(self, x: Tensor) -> np.ndarray:
        """Relative volume change of the joint region per frame ``(F,)`` (``V / V_rest - 1``)."""
        return volume_change(_positions(x), self.mesh.points, self.mesh.cells[self.joint_cells])

    def inverted_tets(self, x: Tensor) -> np.ndarray:
        """Tetrahedra turned inside out (signed volume <= 0) per frame ``(F,)``: such a
        frame has several equilibria (docs/notes/arm3d.md#noticed-left-alone: several
        equilibria near full bend)."""
        return inverted_counts(_positions(x), self.mesh.cells)

    def min_volume_ratio(self, x: Tensor) -> np.ndarray:
        """Per frame ``(F,)``, the smallest volume of a tetrahedron relative to its rest
        volume (``<= 0``: inverted). A frame near a fold has one far below 1 before any
        tetrahedron inverts, so a change of material can fold it (see :meth:`inverted_tets`)."""
        return min_volume_ratios(_positions(x), self.mesh.points, self.mesh.cells)

    def region_summary(self, field: Tensor) -> dict[str, dict[str, float]]:
        """Mean, min, max and volume-weighted mean of ``field`` ``(n_tets,)`` per region (all
        tetrahedra as one region ``body`` when there are no labels); with bounds, the
        tetrahedra and the parameters on each bound (:mod:`.bounds`)."""
        return region_report(field, self.mesh.signed_volumes(), self.regions, self.region_names,
                             self.basis, modulus_bounds(self.cfg))

    def bound_warning(self, at_lower: int, at_upper: int) -> str | None:
        """More than a tenth of the parameters on ``problem.E_min`` / ``E_max``
        (:func:`.bounds.bounds_warning`)."""
        return bounds_warning(self.cfg, self.n_params, at_lower, at_upper)

    def homogeneous_error(self) -> float:
        """Mean surface error of the homogeneous material (computed on first use)."""
        if self._homogeneous is None:
            self._homogeneous = self._baseline()
        return self._homogeneous


def _positions(x: Tensor) -> np.ndarray:
    """Tetrahedron vertex positions ``(F, n, 3)`` as a NumPy array."""
    return x.detach().cpu().numpy()
