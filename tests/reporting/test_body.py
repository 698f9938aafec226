"""Outputs of a 3-D body (torchfit.reporting.body): OBJ frames, VTU, regions, the model
comparison, and TensorBoard meshes and per-frame curves read from a real ``tensorboard``
server through its HTTP data API."""
from __future__ import annotations

import json
from pathlib import Path

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
    surface = problem.observation.surface(problem.simulate(result.field)).numpy()
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


# -- the pictures' colour ranges and the per-frame error plot ------------------------------
def colour_bars(fig):
    """``(label, (low, high))`` of every colour bar of ``fig`` (the colour bar's axes)."""
    return [(ax.get_ylabel(), ax.get_ylim()) for ax in fig.axes if ax.name != "3d"]


def test_the_comparison_range_fits_the_fitted_models_panels_with_a_bar_in_mm():
    from torchfit.reporting.body import comparison_range, surface_figure

    rng = np.random.default_rng(3)
    errors = {("homogeneous", "linear"): 0.010 * rng.random(50),        # far worse
              ("homogeneous", "corotated"): 0.002 * rng.random(50),
              ("fitted", "corotated"): 0.0012 * rng.random(50)}
    vmax = comparison_range(errors, "corotated")
    assert vmax == pytest.approx(float(errors[("homogeneous", "corotated")].max()))
    for key, error in errors.items():        # no panel dark: each reaches a quarter of it
        assert np.percentile(error, 90) >= 0.25 * vmax, key
    assert comparison_range(errors, "linear") == pytest.approx(0.010 * 1.0, rel=0.05)
    mesh = trimesh.creation.icosphere(1)
    faces, vertices = np.asarray(mesh.faces), np.asarray(mesh.vertices)
    error = 0.010 * np.linspace(0, 1, len(vertices))
    fig = surface_figure([("a", vertices, None), ("b", vertices, error),
                          ("c", vertices, 0.5 * error)], faces, 0.004)
    (label, (low, high)), = colour_bars(fig)
    assert label == "surface error (mm)" and (low, high) == pytest.approx((0.0, 4.0))


def test_the_per_frame_errors_show_every_frame_and_mark_the_validation_frames():
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from torchfit.reporting.body import per_frame_errors_figure

    fitted = {0: 1e-3, 1: 2e-3, 3: 1.5e-3}
    fig = per_frame_errors_figure([("fitted", "C0", {**fitted, 2: 3e-3})], [2])
    FigureCanvasAgg(fig).draw()
    ax = fig.axes[0]
    assert sorted(ax.lines[0].get_xdata()) == [0, 1, 2, 3]
    marked = [line for line in ax.lines if line.get_marker() == "s" and len(line.get_xdata())]
    assert [list(line.get_xdata()) for line in marked] == [[2]]
    assert "validation frame (held out of the fit)" in [t.get_text() for t in
                                                         ax.get_legend().get_texts()]
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)


@pytest.fixture(scope="module")
def validated_run(tmp_path_factory):
    """A capsule of four frames fitted with frame 2 held out; every figure the outputs
    drew, by file name."""
    root = tmp_path_factory.mktemp("validated")
    folder = write_capsule(root / "capsule", "skeleton", "npz", angles=(0.0, 10.0, 20.0, 30.0))
    problem = build_problem("animation", {"path": str(folder), "cache_dir": str(root / "cache"),
                                          "tet_edge_length": 0.12, "grid": [2, 2, 3],
                                          "validation_frames": [2]})
    drawn = {}
    monkeypatch = pytest.MonkeyPatch()
    import torchfit.reporting.body as body

    saved = body.save_png

    def keep(fig, path):
        drawn[Path(path).name] = fig
        return saved(fig, path)

    monkeypatch.setattr(body, "save_png", keep)
    try:
        run = root / "run"
        fit(problem, {"name": "levenberg_marquardt", "max_iter": 1, "max_step": 1.0},
            run_dir=run)
    finally:
        monkeypatch.undo()
    return problem, run, drawn


def test_the_error_plot_of_a_fit_holds_its_validation_frames(validated_run):
    problem, run, drawn = validated_run
    assert problem.frame_numbers() == [0, 1, 3]
    ax = drawn["frame_errors.png"].axes[0]
    curves = [line for line in ax.lines if line.get_linestyle() == "-"]
    assert [sorted(line.get_xdata()) for line in curves] == [[0, 1, 2, 3]] * 2  # both materials
    squares = [list(line.get_xdata()) for line in ax.lines if line.get_marker() == "s"
               and len(line.get_xdata())]
    assert squares == [[2], [2]]
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert all(float(t).is_integer() for t in ticks)
    result = json.loads((run / "result.json").read_text())
    fitted = [line for line in ax.lines if line.get_color() == "C0" and
              line.get_linestyle() == "-"][0]
    at_two = dict(zip(fitted.get_xdata(), fitted.get_ydata()))[2]
    # the held-out frame's point is the run's validation error at the end (one frame)
    assert at_two == pytest.approx(1e3 * result["validation"]["final"]["surface_err_mean"])


def test_the_comparison_picture_of_a_fit_has_the_fitted_models_range(validated_run):
    problem, run, drawn = validated_run
    picture = json.loads((run / "model_comparison.json").read_text())["picture"]
    own = [v for k, v in picture["panel_max_mm"].items() if k.endswith("/corotated")]
    assert picture["colour_max_mm"] == pytest.approx(max(own))
    (label, (low, high)), = colour_bars(drawn["frame_comparison.png"])
    assert label == "surface error (mm)" and high == pytest.approx(picture["colour_max_mm"])


def test_regions_and_the_usd_layer_carry_the_fits_uncertainty(capsule_run):
    problem, result, run, _ = capsule_run
    report = result.uncertainty
    assert report.computed and report.gauge      # rig targets: up to the overall scale
    regions = json.loads((run / "regions.json").read_text())["uncertainty"]
    assert regions["sigma_source"] == "residual" and regions["gauge"]
    body = regions["regions"]["body"]
    assert body == pytest.approx(report.regions["body"])
    if body["sd"] is not None:
        assert body["factor"] == pytest.approx(np.exp(2 * body["sd"]))
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(run / "usd" / "body.usda"))
    primvar = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Body")).GetPrimvar(
        "torchfit:youngs_modulus_band")
    band = np.array(primvar.Get(), dtype=np.float64)
    assert band.shape == (len(problem.mesh.cells),)
    assert np.allclose(band, np.exp(2 * report.cell_sd), rtol=1e-12)
    assert "two standard deviations" in primvar.GetAttr().GetCustomDataByKey("torchfit:units")


@pytest.mark.slow
def test_mesh_check_fits_a_second_mesh_and_reports_the_regions_difference(tmp_path):
    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    problem = build_problem("animation", {"path": str(folder), "cache_dir": str(tmp_path / "c"),
                                          "tet_edge_length": 0.12, "grid": [2, 2, 3],
                                          "mesh_check": True})
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 2, "max_step": 1.0},
                 run_dir=tmp_path / "run")
    check = result.uncertainty.mesh_check
    assert check["tets"][0] == len(problem.mesh.cells) and check["tets"][1] != check["tets"][0]
    assert check["setting"]["tet_edge_length"] == pytest.approx(0.108)
    body = check["regions"]["body"]
    # the scale-free body: the second field scaled to the first's mean over the body
    assert body["second"] == pytest.approx(body["first"], rel=1e-9)
    regions = json.loads((tmp_path / "run" / "regions.json").read_text())["uncertainty"]
    assert regions["mesh_check"]["tets"] == check["tets"]
    assert "on a second mesh body" in result.summary()
