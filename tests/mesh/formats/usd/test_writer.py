"""USD out (torchfit.mesh.formats.usd.writer): point caches of simulated frames and a TetMesh with
the fitted field, opened back with usd-core. The skinned rig's writer is checked through the
arm in tests/scripts/test_write_arm.py."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pxr")

from pxr import Sdf, Usd, UsdGeom  # noqa: E402

from helpers.skinned_files import expected_tube, tube, write_tube_usd  # noqa: E402
from torchfit.mesh.formats.usd.writer import (write_point_cache_usd, write_tet_mesh_usd,  # noqa: E402
                                              write_vertex_field_usd)


def test_point_cache_holds_one_time_sample_per_frame(tmp_path):
    points, quads = tube(length=0.2, radius=0.02)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    frames = np.stack([points + [0.01 * f, 0, 0] for f in range(4)])
    write_point_cache_usd(tmp_path / "sim.usda", faces, frames, times=[10, 11, 12, 14])
    stage = Usd.Stage.Open(str(tmp_path / "sim.usda"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Simulated"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [10.0, 11.0, 12.0, 14.0]
    assert mesh.GetExtentAttr().GetTimeSamples() == [10.0, 11.0, 12.0, 14.0]
    assert np.abs(np.array(mesh.GetPointsAttr().Get(14)) - frames[3]).max() < 1e-8
    assert np.allclose(np.array(mesh.GetExtentAttr().Get(14)),
                       [frames[3].min(0), frames[3].max(0)], atol=1e-7)
    assert np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3).tolist() == \
        faces.tolist()
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0


def test_point_cache_over_the_users_stage_in_its_units(tmp_path):
    written = write_tube_usd(tmp_path / "user.usda")               # centimetres, Y up
    rest, frames = expected_tube(written["points"], written["rig"])
    faces = np.concatenate([written["quads"][:, [0, 1, 2]], written["quads"][:, [0, 2, 3]]])
    out = tmp_path / "out" / "simulated.usda"
    out.parent.mkdir()
    write_point_cache_usd(out, faces, frames + 0.001, prim="/Root/Tube_simulated",
                          times=[1, 2, 4], over=tmp_path / "user.usda")
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetPrimAtPath("/Root/Tube").IsValid()             # the original, composed
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Tube_simulated"))
    assert np.abs(np.array(mesh.GetPointsAttr().Get(4)) * 0.01 - (frames[2] + 0.001)).max() \
        < 1e-7                                                 # float32 centimetres
    assert stage.GetRootLayer().subLayerPaths[0] == "../user.usda"


def test_tet_mesh_holds_the_fitted_field(tmp_path):
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    modulus = np.array([1.5e5, 4.0e5])
    write_tet_mesh_usd(tmp_path / "body.usda", points, cells, {"E": modulus})
    stage = Usd.Stage.Open(str(tmp_path / "body.usda"))
    tet = UsdGeom.TetMesh(stage.GetPrimAtPath("/Body"))
    assert np.array(tet.GetTetVertexIndicesAttr().Get()).tolist() == cells.tolist()
    primvar = UsdGeom.PrimvarsAPI(tet.GetPrim()).GetPrimvar("torchfit:E")
    assert primvar.GetInterpolation() == UsdGeom.Tokens.uniform
    assert np.array(primvar.Get()).tolist() == modulus.tolist()
    assert len(tet.GetSurfaceFaceVertexIndicesAttr().Get()) == 6   # two tets share a face
    with pytest.raises(ValueError, match="field E has 3 values for 2 tetrahedra"):
        write_tet_mesh_usd(tmp_path / "bad.usda", points, cells, {"E": [1, 2, 3]})


def test_the_material_as_the_deformable_physics_draft_names_it(tmp_path):
    from pxr import UsdShade

    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])               # volumes 1/6 and 1/3
    material = {"youngsModulus": np.array([1.0, 4.0]), "poissonsRatio": np.full(2, 0.45),
                "density": np.full(2, 1000.0)}
    write_tet_mesh_usd(tmp_path / "body.usda", points, cells, material=material,
                       custom={"torchfit:youngsModulusUnits": "relative to problem.E0"})
    stage = Usd.Stage.Open(str(tmp_path / "body.usda"))
    tet = stage.GetPrimAtPath("/Body")
    for name, values in material.items():
        primvar = UsdGeom.PrimvarsAPI(tet).GetPrimvar(name)
        assert primvar.GetInterpolation() == UsdGeom.Tokens.uniform
        assert np.allclose(primvar.Get(), values)
    bound, _ = UsdShade.MaterialBindingAPI(tet).ComputeBoundMaterial("physics")
    prim = bound.GetPrim()
    assert str(prim.GetPath()) == "/Body/PhysicsMaterial"
    assert list(prim.GetMetadata("apiSchemas").GetAddedOrExplicitItems()) == [
        "OmniPhysicsBaseMaterialAPI", "OmniPhysicsDeformableMaterialAPI"]
    assert prim.GetAttribute("omniphysics:youngsModulus").Get() == pytest.approx(3.0)  # by volume
    assert prim.GetAttribute("omniphysics:poissonsRatio").Get() == pytest.approx(0.45)
    assert prim.GetAttribute("omniphysics:density").Get() == pytest.approx(1000.0)
    assert prim.GetCustomData()["torchfit"]["youngsModulusUnits"] == "relative to problem.E0"


def test_a_vertex_field_on_an_over_of_the_users_mesh(tmp_path):
    written = write_tube_usd(tmp_path / "user.usda")               # centimetres, Y up
    n = len(written["points"])
    values = np.linspace(1.0, 2.0, n)
    out = tmp_path / "out" / "material.usda"
    out.parent.mkdir()
    write_vertex_field_usd(out, "youngsModulus", values, over=tmp_path / "user.usda",
                           prim="/Root/Tube")
    stage = Usd.Stage.Open(str(out))
    mesh = stage.GetPrimAtPath("/Root/Tube")
    primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("youngsModulus")
    assert primvar.GetInterpolation() == UsdGeom.Tokens.vertex
    assert np.allclose(primvar.Get(), values, rtol=1e-7)
    assert len(UsdGeom.Mesh(mesh).GetPointsAttr().Get()) == n     # the user's own mesh
    layer = stage.GetRootLayer()
    assert layer.GetPrimAtPath("/Root/Tube").specifier == Sdf.SpecifierOver
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01


def test_a_layer_of_another_body_is_refused(tmp_path):
    from torchfit.mesh.formats.folder import AnimationError
    from torchfit.mesh.formats.usd.material import layer_cell_values, read_modulus_layer

    points, quads = tube(length=0.2, radius=0.02)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    tets = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    values = np.linspace(1.0, 2.0, len(points))
    common = dict(file_rest=points, file_vertices=None, rest=points, points=points, cells=tets)
    # the same body, moved and scaled (a bind space): accepted, per vertex as painted
    write_vertex_field_usd(tmp_path / "same.usda", "youngsModulus", values,
                           rest=2 * points + 0.1, faces=faces)
    got = layer_cell_values(read_modulus_layer(tmp_path / "same.usda"), "x", **common)
    assert got.shape == (2,) and (got >= 1).all() and (got <= 2).all()
    # as many points, another shape: refused
    bent = points.copy()
    bent[:, 0] += 5 * bent[:, 1] ** 2
    write_vertex_field_usd(tmp_path / "bent.usda", "youngsModulus", values, rest=bent,
                           faces=faces)
    with pytest.raises(AnimationError, match="another body"):
        layer_cell_values(read_modulus_layer(tmp_path / "bent.usda"), "x", **common)
    # another vertex count: refused
    write_vertex_field_usd(tmp_path / "few.usda", "youngsModulus", values[:5],
                           rest=points[:5], faces=faces[:1])
    with pytest.raises(AnimationError, match="5 per-vertex values .* another body"):
        layer_cell_values(read_modulus_layer(tmp_path / "few.usda"), "x", **common)
