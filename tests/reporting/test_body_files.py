"""The files of a simulated body (OBJ sequence, VTU, USD point cache and TetMesh), read back."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from torchfit.reporting.body_files import write_obj_sequence, write_usd

FACES = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
POINTS = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
CELLS = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])


def _surface(frames: int = 3) -> np.ndarray:
    rest = POINTS[:4]
    return np.stack([rest + 0.1 * f * np.array([1.0, -2.0, 0.5]) for f in range(frames)])


def _problem(path: Path, names: list[str], numbers: list[int] | None = None) -> SimpleNamespace:
    numbers = list(range(len(names))) if numbers is None else numbers
    return SimpleNamespace(animation=SimpleNamespace(path=path, faces=FACES, output_faces=FACES,
                                                     file_points=lambda points: points),
                           mesh=SimpleNamespace(points=POINTS, cells=CELLS),
                           frame_names=lambda: names, frame_numbers=lambda: numbers,
                           tet_regions=np.array([0, 1]),
                           cfg=SimpleNamespace(nu=0.45, E0=1.0, E0_unit="relative"),
                           scale_free=True)


def test_obj_sequence_is_whole_or_absent(tmp_path, monkeypatch):
    surface = _surface()
    paths = write_obj_sequence(tmp_path / "frames", surface, FACES)
    assert [p.name for p in paths] == ["frame_000.obj", "frame_001.obj", "frame_002.obj"]
    vertices = [line.split()[1:] for line in paths[2].read_text().splitlines()
                if line.startswith("v ")]
    np.testing.assert_array_equal(np.array(vertices, dtype=float), surface[2])
    assert not list(tmp_path.glob(".*partial"))
    import torchfit.reporting.body_files as body_files

    before = paths[2].read_text()

    written = []

    def full_disk_at_the_third(path, vertices, faces):     # a writer that fails half-way
        if len(written) == 2:
            raise OSError(28, "No space left on device")
        written.append(path)
        Path(path).write_text("v 0 0 0\n")

    monkeypatch.setattr(body_files, "write_obj", full_disk_at_the_third)
    with pytest.raises(OSError):
        write_obj_sequence(tmp_path / "frames", surface + 1, FACES)
    # the earlier complete sequence is kept, untouched; no partial folder is left
    assert (tmp_path / "frames" / "frame_002.obj").read_text() == before
    assert len(written) == 2 and not list(tmp_path.glob(".*partial"))


def test_usd_point_cache_and_tet_mesh_read_back(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    surface = _surface()
    field = np.array([1.5, 0.25])
    files = write_usd(tmp_path, _problem(tmp_path / "anim", ["a", "b", "c"]), surface, field)
    assert [f.name for f in files] == ["frames.usda", "body.usda"]
    stage = Usd.Stage.Open(str(files[0]))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Simulated"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(2.0)), surface[2], atol=1e-7)
    # a subset of a folder's frames (problem.frames=[0,3,11]) keeps their places in the shot
    subset = write_usd(tmp_path / "subset", _problem(tmp_path / "anim", ["a", "b", "c"],
                                                     [0, 3, 11]), surface, field)
    cache = Usd.Stage.Open(str(subset[0]))
    points = UsdGeom.Mesh(cache.GetPrimAtPath("/Simulated")).GetPointsAttr()
    assert points.GetTimeSamples() == [0.0, 3.0, 11.0]
    assert (cache.GetStartTimeCode(), cache.GetEndTimeCode()) == (0.0, 11.0)
    tet_stage = Usd.Stage.Open(str(files[1]))
    tet = tet_stage.GetDefaultPrim()
    assert tet.GetTypeName() == "TetMesh"
    values = UsdGeom.PrimvarsAPI(tet).GetPrimvar("torchfit:youngs_modulus").Get()
    np.testing.assert_array_equal(np.asarray(values), field)


def test_usd_frames_over_the_users_stage_in_its_units_and_times(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    user = tmp_path / "shot.usda"
    stage = Usd.Stage.CreateNew(str(user))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)          # centimetres
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetTimeCodesPerSecond(30)
    stage.GetRootLayer().Save()
    surface = _surface()
    names = [f"shot.usda:/Body@{t}" for t in (101, 103, 105)]
    files = write_usd(tmp_path / "run", _problem(user, names), surface, np.ones(2))
    layered = Usd.Stage.Open(str(files[0]))
    assert UsdGeom.GetStageMetersPerUnit(layered) == pytest.approx(0.01)
    assert UsdGeom.GetStageUpAxis(layered) == UsdGeom.Tokens.y
    assert layered.GetRootLayer().subLayerPaths[0] == "../../shot.usda"
    points = UsdGeom.Mesh(layered.GetPrimAtPath("/Simulated")).GetPointsAttr()
    assert points.GetTimeSamples() == [101.0, 103.0, 105.0]
    np.testing.assert_allclose(np.asarray(points.Get(105.0)), surface[2] / 0.01, rtol=1e-6)


def _embedded_problem(tmp_path, weights: np.ndarray) -> SimpleNamespace:
    """The two-tetrahedron body whose 4 surface vertices are embedded in tets 0, 0, 0, 1 with
    ``weights`` ``(4, 4)``."""
    problem = _problem(tmp_path / "anim", ["a", "b", "c"])
    problem.animation.rest_vertices = POINTS[:4]
    problem.animation.file_values = lambda values: values
    problem.animation.prim = ""
    problem.embedding = SimpleNamespace(cells=np.array([0, 0, 0, 1]), weights=weights)
    return problem


def test_an_embedded_body_writes_its_material_on_the_users_vertices(tmp_path):
    """The per-vertex layer (``usd/material.usda``): the field averaged at the tet vertices
    by volume, then interpolated with each surface vertex's embedding weights."""
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    # vertex 0 sits at tet 0's corner 0; vertex 3 halfway between corners 3 and 4 of tet 1
    problem = _embedded_problem(tmp_path, np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0],
                                                    [0, 0, 1.0, 0], [0, 0, 0.5, 0.5]]))
    field = np.array([1.5, 0.25])
    files = write_usd(tmp_path / "run", problem, _surface(), field)
    assert [f.name for f in files] == ["frames.usda", "body.usda", "material.usda"]
    stage = Usd.Stage.Open(str(files[2]))
    values = np.asarray(UsdGeom.PrimvarsAPI(stage.GetDefaultPrim())
                        .GetPrimvar("youngsModulus").Get())
    volumes = np.array([1.0, 2.0]) / 6.0        # the tetrahedra's volumes
    shared = (1.5 * volumes[0] + 0.25 * volumes[1]) / volumes.sum()   # nodes 1, 2, 3
    expected = [1.5, shared, shared, 0.5 * shared + 0.5 * 0.25]
    np.testing.assert_allclose(values, expected, rtol=1e-6)


def test_rig_json_is_the_problems_rig_or_nothing(tmp_path):
    import json

    from torchfit.reporting.body_files import RIG_FILE, write_rig

    description = {"bones": [{"name": "tip", "length_m": 0.25, "length_from": "derived: x",
                              "driven_vertices": 16}],
                   "attach_radius_m": 0.02, "attach_radius_from": "derived: y",
                   "weights_from": "authored: z"}
    assert write_rig(tmp_path, SimpleNamespace(rig_description=description)) == \
        [tmp_path / RIG_FILE]
    assert json.loads((tmp_path / RIG_FILE).read_text()) == description
    assert write_rig(tmp_path / "none", SimpleNamespace(rig_description=None)) == []
    assert not (tmp_path / "none").exists()


def test_a_body_in_time_writes_its_damping_beside_the_modulus(tmp_path):
    """The fitted Rayleigh damping in both layers (``body.usda``'s TetMesh and
    ``material.usda``'s mesh), next to ``primvars:youngsModulus``, each a double with its
    unit; read back with pxr and with :func:`~torchfit.mesh.formats.usd.read_damping`. A
    quasistatic body writes none."""
    pytest.importorskip("pxr")
    from pxr import Sdf, Usd

    from torchfit.mesh.formats.usd import read_damping

    problem = _embedded_problem(tmp_path, np.eye(4))
    damping = {"alpha": 3.5, "beta": 0.0125, "zeta_w1": 0.25, "w1": 20.5}
    files = write_usd(tmp_path / "run", problem, _surface(), np.array([1.5, 0.25]),
                      damping=damping)
    for path in files[1:]:                    # body.usda, material.usda
        stage = Usd.Stage.Open(str(path))
        prim = stage.GetDefaultPrim()
        alpha = prim.GetAttribute("torchfit:rayleighAlpha")
        assert alpha.GetTypeName() == Sdf.ValueTypeNames.Double and alpha.Get() == 3.5
        assert alpha.GetCustomDataByKey("torchfit:units") == "1/s"
        assert prim.GetAttribute("torchfit:rayleighBeta").Get() == 0.0125
        assert read_damping(path) == {"alpha": (3.5, "1/s"), "beta": (0.0125, "s"),
                                      "zeta_w1": (0.25, "1 (dimensionless)"),
                                      "w1": (20.5, "rad/s")}
    quasistatic = write_usd(tmp_path / "static", problem, _surface(), np.array([1.5, 0.25]))
    assert all(read_damping(path) is None for path in quasistatic[1:])
