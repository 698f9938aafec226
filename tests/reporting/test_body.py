"""Outputs of a 3-D body (torchfit.reporting.body): OBJ frames, VTU, regions, the model
comparison, and TensorBoard meshes and per-frame curves read from a real ``tensorboard``
server through its HTTP data API."""
from __future__ import annotations

import json

import meshio
import numpy as np
import pytest
import trimesh

from helpers.capsule_animation import write_capsule
from helpers.simulations import SimulationCounter
from torchfit import build_problem, fit


@pytest.fixture(scope="module")
def capsule_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("body")
    folder = write_capsule(root / "capsule", "skeleton", "npz")
    problem = build_problem("animation", {"path": str(folder), "cache_dir": str(root / "cache"),
                                          "tet_edge_length": 0.12, "grid": [2, 2, 3]})
    run = root / "run"
    counted = SimulationCounter(problem)
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 2, "max_step": 1.0},
                 run_dir=run)
    # what the fit made (the tests below simulate too)
    return problem, result, run, (dict(counted.per_record), counted.observers, counted.end)


def test_the_body_outputs_read_the_runs_evaluations(capsule_run):
    # one simulation per record, by the run's evaluator; none by the outputs (the OBJ
    # frames, VTU, meshes and the comparison's baseline are the run's evaluations)
    problem, result, run, (per_record, observers, end) = capsule_run
    assert per_record == {i: 1 for i in range(len(result.history))}
    assert observers == 0 and end == 0


def test_simulated_frames_are_obj_files_on_the_users_vertices(capsule_run):
    problem, result, run, _ = capsule_run
    files = sorted((run / "frames").glob("frame_*.obj"))
    assert [f.name for f in files] == ["frame_000.obj", "frame_001.obj", "frame_002.obj"]
    surface = problem.surface(problem.simulate(result.field)).numpy()
    for f, path in enumerate(files):
        mesh = trimesh.load(str(path), process=False, maintain_order=True)
        assert np.array_equal(mesh.faces, problem.animation.faces)
        assert np.allclose(mesh.vertices, surface[f], rtol=0, atol=1e-8)


def test_vtu_holds_the_field_and_every_frames_displacement(capsule_run):
    problem, result, run, _ = capsule_run
    mesh = meshio.read(run / "body.vtu")
    assert np.allclose(mesh.points, problem.mesh.points)
    assert np.array_equal(mesh.cells_dict["tetra"], problem.mesh.cells)
    assert np.allclose(mesh.cell_data["E_relative_to_E0"][0], result.field.numpy())
    x = problem.simulate(result.field).numpy()
    for f in range(problem.n_frames):
        assert np.allclose(mesh.point_data[f"displacement_{f:03d}"], x[f] - problem.mesh.points)


def test_regions_and_model_comparison(capsule_run):
    problem, result, run, _ = capsule_run
    regions = json.loads((run / "regions.json").read_text())
    body = regions["fitted"]["body"]
    assert body["tets"] == problem.model.n_cells
    assert body["min"] <= body["volume_mean"] <= body["max"]
    comparison = json.loads((run / "model_comparison.json").read_text())
    assert set(comparison["homogeneous"]) == {"linear", "corotated"}
    assert comparison["frame"] == problem.full_bend_frame == 2
    saved = json.loads((run / "result.json").read_text())["model_comparison"]
    assert saved["fitted"]["corotated"]["surface_err_mean"] == pytest.approx(
        result.metrics["surface_err_mean"])
    assert (run / "frame_comparison.png").stat().st_size > 10_000
    assert (run / "frame_errors.png").is_file()


def test_tensorboard_shows_meshes_and_per_frame_curves(capsule_run, tensorboard_server):
    problem, result, run, _ = capsule_run
    server = tensorboard_server(run / "tb")
    tags = server.wait_until(lambda: server.get("/data/plugin/mesh/tags"), what="mesh tags")
    (run_name, mesh_tags), = tags.items()
    frames = sorted({0, problem.full_bend_frame})
    assert set(mesh_tags) == {f"mesh/{kind}_frame{f}" for f in frames
                              for kind in ("surface_error", "E")}
    meta = server.get("/data/plugin/mesh/meshes", run=run_name,
                      tag=f"mesh/surface_error_frame{frames[-1]}", sample=0)
    # content types of the mesh plugin's proto: 1 vertices, 2 faces, 3 colours
    shapes = {m["content_type"]: m["data_shape"] for m in meta}
    assert shapes[1] == shapes[3] == [1, problem.animation.n_vertices, 3]
    assert shapes[2] == [1, len(problem.animation.faces), 3]
    curves = server.scalars(run_name, "frames/surface_err_mean")
    assert [step for step, _ in curves] == list(range(problem.n_frames))
    per_frame = problem.frame_errors(problem.simulate(result.field))
    assert np.allclose([v for _, v in curves], per_frame["surface_err_mean"], rtol=1e-6)
    inverted = server.scalars(run_name, f"frames/inverted_tets_{problem.cfg.model.value}")
    assert [v for _, v in inverted] == per_frame["inverted_tets"].tolist()


def test_frames_with_inverted_tetrahedra_are_named_in_one_warning(caplog):
    from torchfit.reporting.body import warn_inverted

    with caplog.at_level("WARNING", logger="torchfit.progress"):
        warn_inverted(np.array([0, 0, 3, 4, 0, 1, 0]))
        warn_inverted(np.zeros(5, dtype=int))       # nothing inverted: nothing said
        # a subset of the animation (problem.frames): named by the animation's numbers
        warn_inverted(np.array([0, 2, 5, 0, 0]), [0, 6, 9, 30, 40])
        warn_inverted(np.array([1, 2]), [9, 11])   # no other frame: no continuation to suggest
        warn_inverted(np.array([0, 2]), [0, 9], suggest=False)   # an init= run: it is one
    first, subset, alone, continued = (r.getMessage() for r in caplog.records)
    assert "frame 9 has tetrahedra" in continued and "problem.frames" not in continued
    assert "continuation" not in continued and "continuation" not in alone
    assert "frames 2-3, 5 have tetrahedra turned inside out" in first
    assert "(at most 4)" in first and "'problem.frames=[0,1,4,6]'" in first
    assert "frames 6, 9 have" in subset and "'problem.frames=[0,30,40]'" in subset
    assert "continuation=true" in subset and "init=<that run's directory>" in subset
    assert "frames 9-11 have" not in alone and "frames 9, 11 have" in alone
    assert "problem.frames" not in alone


def test_the_fold_warning_points_at_the_problems_docs_only_where_it_has_them(caplog):
    from torchfit.reporting.body import warn_inverted

    with caplog.at_level("WARNING", logger="torchfit.progress"):
        warn_inverted(np.array([0, 2]), [0, 9])
        warn_inverted(np.array([0, 2]), [0, 9], docs="docs/notes/arm3d.md, 'Several'")
    plain, arm = (r.getMessage() for r in caplog.records)
    assert "docs/" not in plain and "(docs/notes/arm3d.md, 'Several')" in arm


def test_the_comparison_picture_turns_the_body_into_the_camera_axes():
    """``view`` rows right, depth, up: a body seen through its own camera axes is drawn as
    the unturned body seen through the world's (the same picture, to
    round-off in a few edge pixels)."""
    from scipy.spatial.transform import Rotation

    from torchfit.reporting.body import surface_figure

    mesh = trimesh.creation.capsule(height=0.3, radius=0.05, count=[8, 8])
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    vertices = vertices + 0.1 * vertices[:, 2:3] ** 2 * [1.0, 0.0, 0.0]      # a bend
    turn = Rotation.from_euler("xyz", [20.0, -60.0, 100.0], degrees=True).as_matrix()

    def pixels(points, view):
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        canvas = FigureCanvasAgg(surface_figure([("a", points, None)], faces, 1.0, view=view))
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())

    def differ(a, b):                   # share of pixels that differ
        return float(np.any(a != b, axis=-1).mean())

    world = pixels(vertices, None)
    assert differ(pixels(vertices @ turn.T, turn.T), world) < 1e-3     # camera turned along
    assert differ(pixels(vertices @ turn.T, None), world) > 1e-2       # a fixed camera: not


@pytest.mark.parametrize("unit", ["relative", "Pa"])
def test_every_modulus_that_leaves_the_tool_says_its_unit(tmp_path, unit, caplog):
    """``problem.E0=2``: relative to E0 the files hold the field / 2 and say so; with
    ``E0_unit=Pa`` they hold pascals. USD attributes (``customData``, documentation), the
    VTU field's name and ``result.json`` all say which. Bounds of [0.9, 1.1] E0 hold most
    parameters: one warning line names the bound and the setting that moves it."""
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    problem = build_problem("animation", {"path": str(folder), "cache_dir": str(tmp_path / "c"),
                                          "tet_edge_length": 0.12, "grid": [2, 2, 3],
                                          "E0": 2.0, "E0_unit": unit, "E_min": 0.9,
                                          "E_max": 1.1})
    run = tmp_path / "run"
    with caplog.at_level("WARNING", logger="torchfit.run"):
        result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 2, "max_step": 1.0},
                     run_dir=run)
    field = result.field.numpy()
    factor, label = (0.5, "relative to problem.E0") if unit == "relative" else (1.0, "Pa")
    vtu = meshio.read(run / "body.vtu")
    name = "E_relative_to_E0" if unit == "relative" else "E_Pa"
    assert "E" not in vtu.cell_data
    np.testing.assert_allclose(vtu.cell_data[name][0], factor * field, rtol=1e-12)
    saved = json.loads((run / "result.json").read_text())["modulus_units"]
    assert saved["unit"] == label and saved["E0"] == 2.0
    assert ("to_pascals" in saved) == (unit == "relative")
    stage = Usd.Stage.Open(str(run / "usd" / "body.usda"))      # (kept: prims need it)
    tet = stage.GetDefaultPrim()
    for primvar in ("torchfit:youngs_modulus", "youngsModulus"):
        attribute = UsdGeom.PrimvarsAPI(tet).GetPrimvar(primvar).GetAttr()
        assert attribute.GetCustomDataByKey("torchfit:units") == label
        assert label in attribute.GetDocumentation()
        np.testing.assert_allclose(np.asarray(attribute.Get()), factor * field, rtol=1e-6)
    assert tet.GetCustomDataByKey("torchfit:youngsModulusUnits") == label
    layered = Usd.Stage.Open(str(run / "usd" / "material.usda"))
    layer = layered.GetDefaultPrim()
    vertex = UsdGeom.PrimvarsAPI(layer).GetPrimvar("youngsModulus").GetAttr()
    assert vertex.GetCustomDataByKey("torchfit:units") == label
    # the bound: more than a tenth of the 12 parameters end on [1.8, 2.2]
    last = result.history[-1]
    on = int(last["at_lower_bound"] + last["at_upper_bound"])
    lines = [r.getMessage() for r in caplog.records if "ended on a bound" in r.getMessage()]
    assert (len(lines) == 1) == (on > 1.2)
    if lines:
        assert f"{on} of 12 parameters ended on a bound" in lines[0]
        assert "problem.E_min=" in lines[0] or "problem.E_max=" in lines[0]
