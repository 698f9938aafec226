"""A material layer from a DCC: per-vertex or per-tetrahedron ``youngsModulus`` (the extra ``usd``).

:func:`read_damping` reads back the Rayleigh damping a fit in time wrote beside the modulus
(``torchfit:rayleighAlpha`` in 1/s, ``torchfit:rayleighBeta`` in s, ...).

``problem.init_field=<file>.usd[a|c|z]`` starts a fit from a field an artist painted, or one
torchfit wrote (``usd/material.usda``, ``usd/body.usda`` of a run). :func:`read_modulus_layer`
reads the stage's first prim (depth first) that carries one of

- ``primvars:youngsModulus`` with ``vertex`` (or ``varying``) interpolation on a
  ``UsdGeom.Mesh``: one value per point of the user's mesh, in its order (an ``over`` of
  the user's prim composes with the user's points);
- ``primvars:youngsModulus`` with ``uniform`` interpolation (or the older
  ``primvars:torchfit:youngs_modulus``) on a ``UsdGeom.TetMesh``: one value per tetrahedron,

with the prim's rest points in metres (the stage's ``metersPerUnit``, the prim's transform
at the default time) and, for a TetMesh, its tetrahedra. Whether the layer belongs to the
body being fitted is the caller's check (:func:`layer_cell_values`). Errors are one line
(:class:`~torchfit.mesh.AnimationError`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ...animation import AnimationError

#: a layer's points must match the body's within this fraction of its bounding box's diagonal
MATCH_TOLERANCE = 1e-3


@dataclasses.dataclass
class ModulusLayer:
    """What :func:`read_modulus_layer` found.

    Attributes:
        kind: ``"vertex"`` (values per mesh point) or ``"tet"`` (values per tetrahedron).
        values: ``(V,)`` or ``(m,)`` Young's moduli as written (in ``unit``; a
            quasistatic fit is scale-free, so they are a starting shape).
        points: ``(V, 3)`` or ``(n, 3)`` rest points of the prim, metres (``None`` where the
            layer holds no points, e.g. an ``over`` without the user's stage).
        cells: ``(m, 4)`` tetrahedra of a TetMesh, else ``None``.
        prim: the prim's path.
        unit: the values' unit as the layer says it (``customData`` ``torchfit:units`` on
            the attribute, or ``torchfit:youngsModulusUnits`` on it or its prim, as torchfit
            writes them): ``"Pa"``, ``"relative to problem.E0"``, or ``""`` where the layer
            says none (a painted one).
    """

    kind: str
    values: np.ndarray
    points: np.ndarray | None
    cells: np.ndarray | None
    prim: str
    unit: str = ""

    @property
    def relative(self) -> bool:
        """Whether the values are factors of a homogeneous modulus (``relative ...``)."""
        return self.unit.startswith("relative")


def read_modulus_layer(path: str | Path) -> ModulusLayer:
    """The first per-vertex or per-tetrahedron ``youngsModulus`` of the stage at ``path``."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise AnimationError(f"{path}: no such file; give a USD layer with primvars:"
                             "youngsModulus (per vertex of your mesh or per tetrahedron)")
    try:
        from pxr import Usd, UsdGeom
    except ImportError as err:
        raise AnimationError(f"{path}: reading USD needs the optional extra 'usd': pip install "
                             f"'torchfit[usd]' ({err})") from err
    from .reader import open_stage

    stage = open_stage(path)
    scale = float(UsdGeom.GetStageMetersPerUnit(stage))
    for prim in stage.Traverse():
        primvars = UsdGeom.PrimvarsAPI(prim)
        for name in ("youngsModulus", "torchfit:youngs_modulus"):
            primvar = primvars.GetPrimvar(name)
            if not primvar or not primvar.HasAuthoredValue():
                continue
            values = np.array(primvar.Get(), dtype=np.float64).reshape(-1)
            interpolation = primvar.GetInterpolation()
            is_tet = prim.IsA(UsdGeom.TetMesh)
            kind = "tet" if is_tet and interpolation == UsdGeom.Tokens.uniform else \
                "vertex" if interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) \
                else ""
            if not kind:
                raise AnimationError(f"{path}:{prim.GetPath()}: primvars:{name} has "
                                     f"{interpolation} interpolation; give it per vertex "
                                     "(vertex) on a mesh or per tetrahedron (uniform) on a "
                                     "TetMesh")
            if not np.isfinite(values).all() or (values <= 0).any():
                raise AnimationError(f"{path}:{prim.GetPath()}: primvars:{name} holds a value "
                                     "that is not a positive finite modulus")
            points = None
            raw = UsdGeom.PointBased(prim).GetPointsAttr().Get() \
                if prim.IsA(UsdGeom.PointBased) else None
            if raw is not None and len(raw):
                local = np.array(raw, dtype=np.float64).reshape(-1, 3)
                matrix = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(
                    Usd.TimeCode.Default()), dtype=np.float64).reshape(4, 4)
                points = (local @ matrix[:3, :3] + matrix[3, :3]) * scale
            cells = None
            if is_tet:
                cells = np.array(UsdGeom.TetMesh(prim).GetTetVertexIndicesAttr().Get(),
                                 dtype=np.int64).reshape(-1, 4)
            return ModulusLayer(kind, values, points, cells, str(prim.GetPath()),
                                _unit(primvar.GetAttr(), prim))
    raise AnimationError(f"{path}: no prim carries primvars:youngsModulus (per vertex of a "
                         "mesh or per tetrahedron of a TetMesh)")


#: the damping a run in time writes beside the modulus (torchfit's own attributes: the
#: deformable-physics draft names none; docs/guide/dcc.md): attribute -> key
DAMPING_KEYS = {"torchfit:rayleighAlpha": "alpha", "torchfit:rayleighBeta": "beta",
                "torchfit:dampingRatioLowestMode": "zeta_w1",
                "torchfit:lowestAngularFrequency": "w1"}


def read_damping(path: str | Path) -> dict[str, tuple[float, str]] | None:
    """The fitted Rayleigh damping a run in time wrote into the layer at ``path``
    (``usd/material.usda`` or ``usd/body.usda``): ``{key: (value, unit)}`` for the
    attributes of :data:`DAMPING_KEYS` on the first prim that carries
    ``torchfit:rayleighAlpha`` (``alpha`` in 1/s, ``beta`` in s, ``zeta_w1`` the damping ratio
    at the lowest mode, ``w1`` in rad/s), the unit from the attribute's ``customData``
    (``torchfit:units``); ``None`` where no prim carries it (a quasistatic fit)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(Path(path).expanduser()))
    if stage is None:
        raise AnimationError(f"{path}: cannot open it as a USD stage")
    for prim in stage.Traverse():
        if not prim.HasAttribute("torchfit:rayleighAlpha"):
            continue
        out = {}
        for name, key in DAMPING_KEYS.items():
            attribute = prim.GetAttribute(name)
            if attribute and attribute.HasAuthoredValue():
                out[key] = (float(attribute.Get()),
                            str(attribute.GetCustomDataByKey("torchfit:units") or ""))
        return out
    return None


def _unit(attribute, prim) -> str:
    """The unit the layer writes for ``attribute`` (:attr:`ModulusLayer.unit`)."""
    for holder, key in ((attribute, "torchfit:units"), (attribute, "torchfit:youngsModulusUnits"),
                        (prim, "torchfit:youngsModulusUnits")):
        value = holder.GetCustomDataByKey(key)
        if isinstance(value, str) and value.strip():
            return value.strip()
    return ""


def layer_cell_values(layer: ModulusLayer, where: str, *, file_rest: np.ndarray,
                      file_vertices: np.ndarray | None, rest: np.ndarray, points: np.ndarray,
                      cells: np.ndarray) -> np.ndarray:
    """The layer's modulus per tetrahedron ``(m,)`` of the body being fitted, or one
    :class:`~torchfit.mesh.AnimationError` line when the layer belongs to another body.

    Args:
        file_rest: ``(V_file, 3)`` the user's rest vertices in the file's order (metres);
            file_vertices: ``(V_file,)`` their welded vertex (``None``: the same);
            rest: ``(V, 3)`` the welded rest surface; points, cells: the body's tet mesh.

    A per-vertex layer must have the file's vertex count (and, where it holds points, the
    same rest points up to an affine map, within ``MATCH_TOLERANCE`` of the diagonal: a
    skinned mesh's points may lie in its bind space); each tetrahedron takes the
    value of the surface vertex nearest its centroid (as region labels are carried inward),
    copies of a welded vertex averaged. A per-tetrahedron layer of the same tet mesh is taken
    as it is; one of another tetrahedralisation of the same body (its points within the
    body's bounding box, to the tolerance) gives each tetrahedron the value of the layer's
    tetrahedron whose centroid is nearest.
    """
    diagonal = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    tolerance = MATCH_TOLERANCE * diagonal
    centroids = points[cells].mean(axis=1)
    if layer.kind == "vertex":
        if len(layer.values) != len(file_rest):
            raise AnimationError(f"{where}: {len(layer.values)} per-vertex values on "
                                 f"{layer.prim}, but the animation's mesh has {len(file_rest)} "
                                 "vertices: it is a layer of another body; paint the mesh "
                                 "that is fitted")
        if layer.points is not None and len(layer.points) == len(file_rest):
            # up to an affine map: a skinned mesh's own points may sit in another space
            # (its geomBindTransform, the skeleton's transform) than the posed rest
            homogeneous = np.concatenate([layer.points, np.ones((len(file_rest), 1))], 1)
            fit = np.linalg.lstsq(homogeneous, file_rest, rcond=None)[0]
            gap = float(np.linalg.norm(homogeneous @ fit - file_rest, axis=1).max())
            if gap > tolerance:
                raise AnimationError(f"{where}: the points of {layer.prim} lie up to {gap:.3g} m "
                                     "from the animation's rest vertices: it is a layer of "
                                     "another body (or another pose); paint the mesh that is "
                                     "fitted, at rest")
        values = layer.values
        if file_vertices is not None:
            total = np.bincount(file_vertices, weights=values, minlength=len(rest))
            values = total / np.maximum(np.bincount(file_vertices, minlength=len(rest)), 1)
        _, nearest = cKDTree(rest).query(centroids)
        return values[nearest]
    if layer.points is None or layer.cells is None:
        raise AnimationError(f"{where}: the TetMesh {layer.prim} has no points or tetrahedra")
    if len(layer.cells) != len(layer.values):
        raise AnimationError(f"{where}: {len(layer.values)} per-tetrahedron values for the "
                             f"{len(layer.cells)} tetrahedra of {layer.prim}")
    if layer.points.shape == points.shape and len(layer.cells) == len(cells) and \
            np.array_equal(layer.cells, cells) and \
            float(np.abs(layer.points - points).max()) <= tolerance:
        return layer.values.copy()
    lo, hi = points.min(0), points.max(0)
    gap = max(float(np.abs(layer.points.min(0) - lo).max()),
              float(np.abs(layer.points.max(0) - hi).max()))
    if gap > 20 * tolerance:
        raise AnimationError(f"{where}: the TetMesh {layer.prim} spans another box than the "
                             f"body (up to {gap:.3g} m off): it is a layer of another body")
    _, nearest = cKDTree(layer.points[layer.cells].mean(axis=1)).query(centroids)
    return layer.values[nearest]
