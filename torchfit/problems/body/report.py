"""What a run reports of a body fitted to an animation: pure functions on arrays (and its description).

Positions are ``(F, n, 3)`` arrays of the tetrahedron vertices in every frame, ``cells``
``(m, 4)`` positively oriented at rest, ``rest_points`` ``(n, 3)``; volumes are signed
(``<= 0``: inverted). Surface errors are distances (metres) of surface vertices to their
noise-free targets, ``(F, V)`` tensors.
"""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...mesh import signed_volumes
from ...physics.elasticity import get_material

#: a value within this relative distance of a bound is on it (region_summary's bounds)
ON_BOUND_RTOL = 1e-6

#: the body metrics (docs/problems.md) after the generic ones, in this order
BODY_METRICS = ("surface_err_mean", "surface_err_max", "surface_err_reduction",
                "joint_volume_change", "inverted_tets")


def frame_volumes(positions: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed volumes ``(F, m)`` of ``cells`` in every frame (frame by frame: the corner array
    of 48 frames of 10k tetrahedra would be 110 MB)."""
    return np.stack([signed_volumes(frame, cells) for frame in positions])


def volume_change(positions: np.ndarray, rest_points: np.ndarray,
                  cells: np.ndarray) -> np.ndarray:
    """Relative volume change ``(F,)`` of ``cells`` taken together (``V / V_rest - 1``)."""
    rest = float(signed_volumes(rest_points, cells).sum())
    return frame_volumes(positions, cells).sum(axis=1) / rest - 1.0


def inverted_counts(positions: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Tetrahedra turned inside out (signed volume ``<= 0``) per frame ``(F,)``."""
    return (frame_volumes(positions, cells) <= 0).sum(axis=1)


def min_volume_ratios(positions: np.ndarray, rest_points: np.ndarray,
                      cells: np.ndarray) -> np.ndarray:
    """Per frame ``(F,)``, the smallest volume of a tetrahedron relative to its rest volume."""
    rest = signed_volumes(rest_points, cells)
    return (frame_volumes(positions, cells) / rest[None]).min(axis=1)


def surface_distances(simulated: Tensor, targets: Tensor) -> Tensor:
    """Distance of every vertex to its target, ``(..., V, 3)`` each -> ``(..., V)``."""
    return torch.linalg.vector_norm(simulated - targets, dim=-1)


def body_metrics(errors: Tensor, homogeneous_error: float, joint_change: np.ndarray,
                 inverted: np.ndarray, reference_frame: int) -> dict[str, float]:
    """The keys of :data:`BODY_METRICS`: mean and max surface error ``errors`` ``(F, V)``,
    how far the mean is below the homogeneous material's (``inf`` at zero error), the joint's
    volume change in the reference frame, the most inverted tetrahedra of any frame."""
    out = {"surface_err_mean": float(errors.mean()), "surface_err_max": float(errors.max())}
    mean = out["surface_err_mean"]
    out["surface_err_reduction"] = homogeneous_error / mean if mean > 0 else math.inf
    out["joint_volume_change"] = float(joint_change[reference_frame])
    out["inverted_tets"] = float(inverted.max())
    return out


def frame_report(errors: Tensor, joint_change: np.ndarray,
                 inverted: np.ndarray) -> dict[str, np.ndarray]:
    """Per frame ``(F,)``: mean and max surface error, joint volume change, inverted tets."""
    return {"surface_err_mean": errors.mean(dim=1).cpu().numpy(),
            "surface_err_max": errors.amax(dim=1).cpu().numpy(),
            "joint_volume_change": joint_change, "inverted_tets": inverted}


def region_summary(values: np.ndarray, volumes: np.ndarray, labels: np.ndarray | None,
                   names: list[str], bounds: tuple[float, float] | None = None
                   ) -> dict[str, dict[str, float]]:
    """Count, volume, mean, min, max and volume-weighted mean of per-cell ``values`` per
    region (``labels`` ``(m,)`` indexing ``names``; all cells as one region ``body`` when
    ``labels`` is ``None``); regions without cells are left out. With ``bounds``
    ``(low, high)``, also the fractions of the region's cells on each bound (``at_lower``,
    ``at_upper``: within a relative 1e-6 of it)."""
    labels = labels if labels is not None else np.zeros(len(values), dtype=np.int64)
    out = {}
    for r, name in enumerate(names or ["body"]):
        mask = labels == r
        if not mask.any():
            continue
        out[name] = {"tets": int(mask.sum()), "volume": float(volumes[mask].sum()),
                     "mean": float(values[mask].mean()), "min": float(values[mask].min()),
                     "max": float(values[mask].max()),
                     "volume_mean": float((values[mask] * volumes[mask]).sum()
                                          / volumes[mask].sum()),
                     **fraction_on_bounds(values[mask], bounds)}
    return out


def fraction_on_bounds(values, bounds: tuple[float, float] | None) -> dict[str, float]:
    """``{'at_lower': ..., 'at_upper': ...}``: fractions of ``values`` (a region's
    tetrahedra) on each bound (``{}`` without bounds)."""
    if bounds is None or len(values) == 0:
        return {}
    low, high = bounds
    return {"at_lower": float((values <= low * (1 + ON_BOUND_RTOL)).mean()),
            "at_upper": float((values >= high * (1 - ON_BOUND_RTOL)).mean())}


def describe_body(problem: Any, bounds: Any) -> dict[str, Any]:
    """The sizes, mesh, rig and settings a rigged body adds to ``describe()`` (result.json);
    ``bounds``: its modulus bounds (:func:`.bounds.modulus_bounds`)."""
    out = {"model": get_material(problem.cfg.model.value).name, "nu": problem.model.nu,
           "animation": str(problem.animation.path), "n_frames": problem.n_frames,
           "n_tets": problem.model.n_cells, "n_vertices": problem.model.n_vertices,
           "n_surface_vertices": problem.animation.n_vertices,
           "n_dirichlet": int(len(problem.dirichlet_vertices)),
           "n_free_dofs": 3 * (problem.model.n_vertices - len(problem.dirichlet_vertices)),
           "tet_cache_hit": bool(problem.tet.from_cache), "tet_key": problem.tet.key,
           "tetrahedralize_s": float(problem.tet.build_seconds),
           "backend": problem.backend, "full_bend_frame": problem.full_bend_frame,
           "joint_tets": int(len(problem.joint_cells)), "grid": problem.grid.describe(),
           "E_bounds": bounds,
           "surface_err_mean_homogeneous": problem.report.homogeneous_error()}
    if problem.rig_report is not None:     # the rig check's largest skinning distance
        out["rig_skinning_error"] = problem.rig_report.skinning_error
    if os.environ.get("TORCHFIT_CACHE_DIR"):
        out["cache_dir"] = os.environ["TORCHFIT_CACHE_DIR"]
    return out
