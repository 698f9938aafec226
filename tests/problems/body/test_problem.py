"""problem=animation (torchfit.problems.body.problem): a user's rigged animation, end to end
through real pytetwild.

The capsule of tests/helpers/capsule_animation.py (a second closed surface, two bones, three
frames) goes through the loader, tetrahedralisation (cached), embedding, both driving modes,
a fit, and the bad-input errors of the issue as the user sees them (the format's and the
rig's own messages: tests/mesh/test_animation_format.py, tests/mesh/test_rig.py).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.capsule_animation import write_capsule
from helpers.fit_app import run_fit_app
from helpers.log_records import warned
from torchfit import build_problem, fit
from torchfit.problems import ProblemConfigError

DATA = Path(__file__).resolve().parents[2] / "data"
SMALL = {"tet_edge_length": 0.12, "grid": [2, 2, 3], "newton_rtol": 1e-9}


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("TORCHFIT_CACHE_DIR", str(folder))
    return folder


def problem_for(folder, cache, **settings):
    return build_problem("animation", {"path": str(folder), "cache_dir": str(cache),
                                       **SMALL, **settings})


@pytest.mark.parametrize("mode,frames_as", [("skeleton", "obj"), ("driven", "npz")])
def test_capsule_fits_and_rerun_hits_the_tet_cache(tmp_path, cache, mode, frames_as):
    folder = write_capsule(tmp_path / "capsule", mode, frames_as)
    problem = problem_for(folder, cache, target="synthetic", truth="blocks",
                          E_blocks=[1.0, 3.0, 0.5])
    assert not problem.tet.from_cache
    assert problem.n_frames == 3
    assert (problem.mesh.signed_volumes() > 0).all()
    # the user's surface vertices are embedded: the rest tets reproduce them exactly
    rest = torch.as_tensor(problem.mesh.points)
    assert torch.allclose(problem.observation.surface(rest), torch.as_tensor(problem.animation.rest_vertices),
                          atol=1e-12)
    if mode == "driven":
        assert problem.observed_vertices.numel() == int((~problem.animation.driven.mask).sum())
    else:
        assert problem.observed_vertices.numel() == problem.animation.n_vertices
    # pytetwild's mesh differs from run to run (1.8k-4.2k tets here): on most meshes LM
    # recovers the field to 1e-8, but on some it stops in a local minimum (a CI mesh of
    # 2026-11-25: misfit 3.2e-3 -> 8.7e-4 and flat, `k_err_rel_aligned` 0.12, no tetrahedron
    # near a fold). The fit on a fresh mesh must lower the misfit; the recovery is asserted
    # on a kept mesh (test_capsule_recovers_the_blocks_on_a_kept_mesh).
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 40, "max_step": 1.0})
    assert result.metrics["misfit"] < 0.5 * result.history[0]["misfit"]
    again = problem_for(folder, cache, target="synthetic", truth="blocks",
                        E_blocks=[1.0, 3.0, 0.5])
    assert again.tet.from_cache
    assert np.array_equal(again.tet.points, problem.tet.points)
    assert np.array_equal(again.tet.cells, problem.tet.cells)


@pytest.mark.parametrize("mode,frames_as", [("skeleton", "obj"), ("driven", "npz")])
def test_capsule_recovers_the_blocks_on_a_kept_mesh(tmp_path, mode, frames_as):
    """The capsule's mesh kept in tests/data/capsule_mesh (2,350 tets, pytetwild 2026-11-25;
    stored in the body's principal frame since 2026-11-26, torchfit.problems.body.frame):
    noise-free blocks are recovered to 1e-3 (3.7e-8 and 6.9e-9 measured) in each mode."""
    shutil.copytree(DATA / "capsule_mesh", tmp_path / "cache")
    folder = write_capsule(tmp_path / "capsule", mode, frames_as)
    problem = problem_for(folder, tmp_path / "cache", target="synthetic", truth="blocks",
                          E_blocks=[1.0, 3.0, 0.5])
    assert problem.tet.from_cache, "the capsule's surface or mesh options changed: keep a " \
        "new mesh in tests/data/capsule_mesh"
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 40, "max_step": 1.0})
    assert result.metrics["k_err_rel_aligned"] < 1e-3
    assert result.metrics["surface_err_mean"] < 1e-6


@pytest.mark.slow
def test_rig_target_fit_lowers_the_surface_error(tmp_path, cache):
    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    problem = problem_for(folder, cache)
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 6, "max_step": 1.0})
    assert result.metrics["surface_err_reduction"] > 1.0
    assert result.metrics["surface_err_mean"] < problem.report.homogeneous_error()


def test_fit_app_runs_the_capsule_end_to_end(tmp_path, cache):
    folder = write_capsule(tmp_path / "capsule", "skeleton", "obj")
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=animation", f"problem.path={folder}",
                       f"problem.cache_dir={cache}", "problem.tet_edge_length=0.12",
                       "problem.grid=[2,2,3]", "solver.max_iter=3", "threads=1")
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((run / "result.json").read_text())
    assert result["problem"]["n_frames"] == 3
    assert result["surface_err_mean"] <= result["problem"]["surface_err_mean_homogeneous"]


# -- bad input: one clear line, before any output -------------------------------------
def expect_error(folder, cache, match, **settings):
    with pytest.raises(ProblemConfigError, match=match) as info:
        problem_for(folder, cache, **settings)
    assert "\n" not in str(info.value)


def test_a_bad_animation_folder_is_one_line_naming_problem_path(tmp_path, cache):
    """The format's errors (tests/mesh/test_animation_format.py) reach the user as one
    ProblemConfigError line naming the setting."""
    expect_error(tmp_path / "nowhere", cache, f"^problem.path={tmp_path / 'nowhere'}: no "
                 "animation manifest at")
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    frames = np.load(folder / "frames.npz")["frames"]
    frames[2, 17, 1] = np.nan
    np.savez(folder / "frames.npz", frames=frames)
    expect_error(folder, cache, f"^problem.path={folder}: .*frame 2 .*vertex 17 has a NaN")


def test_a_rig_that_holds_nothing_names_the_animation(tmp_path, cache):
    """The drive's errors (tests/mesh/test_rig.py) name the animation's manifest."""
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    with np.load(folder / "skeleton.npz") as data:
        bones = {k: data[k] for k in data.files}
    bones["heads"] = bones["heads"] + [1.0, 0, 0]
    bones["tails"] = bones["tails"] + [1.0, 0, 0]
    np.savez(folder / "skeleton.npz", **bones)
    expect_error(folder, cache, r"animation\.yaml: no material point lies within attach_radius")


def test_broken_surface_is_an_error_and_an_open_one_a_warning(tmp_path, cache, caplog):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    import trimesh

    mesh = trimesh.load(str(folder / "rest.obj"), process=False, maintain_order=True)
    flat = np.asarray(mesh.vertices).copy()
    flat[:, 0] = 0.0                                    # every vertex on one plane
    trimesh.Trimesh(flat, mesh.faces, process=False).export(str(folder / "rest.obj"))
    np.savez(folder / "frames.npz", frames=np.broadcast_to(flat, (3, *flat.shape)))
    with pytest.raises(ProblemConfigError, match="tetrahedr") as info:
        problem_for(folder, cache)
    assert "\n" not in str(info.value)
    folder = write_capsule(tmp_path / "open", "skeleton", "npz")
    mesh = trimesh.load(str(folder / "rest.obj"), process=False, maintain_order=True)
    keep = np.ones(len(mesh.faces), dtype=bool)
    keep[np.argsort(mesh.triangles_center[:, 2])[-4:]] = False   # a hole at the top
    trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False).export(
        str(folder / "rest.obj"))
    problem = problem_for(folder, cache)
    (line,) = warned(caplog, "rest surface: .*(watertight|open)")
    assert "\n" not in line
    assert problem.model.n_cells > 0


def test_app_reports_bad_animation_in_one_line_and_writes_nothing(tmp_path, cache):
    folder = write_capsule(tmp_path / "c", "driven", "npz")
    np.save(folder / "driven.npy", np.zeros(0, dtype=np.int64))
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=animation", f"problem.path={folder}",
                       f"problem.cache_dir={cache}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [l for l in proc.stderr.strip().splitlines() if l.strip()]
    assert len(lines) == 1 and "driven set is empty" in lines[0], proc.stderr
    assert not (run / "result.json").exists() and not (run / "tb").exists()


def test_app_reports_a_usd_stage_without_skinned_mesh_in_one_line(tmp_path, cache):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    path = tmp_path / "still.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Mesh.Define(stage, "/Still").CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    stage.GetRootLayer().Save()
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=animation", f"problem.path={path}",
                       f"problem.cache_dir={cache}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [l for l in proc.stderr.strip().splitlines() if l.strip()]
    assert len(lines) == 1 and "no skinned mesh" in lines[0], proc.stderr
    assert not (run / "result.json").exists()


def test_negative_fps_is_refused_before_reading(tmp_path):
    from torchfit import build_problem
    from torchfit.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match=r"^problem.fps=-1.0: must be >= 0"):
        build_problem("animation", {"path": str(tmp_path / "a.glb"), "fps": -1.0})


@pytest.mark.parametrize("suffix, extra", [(".usda", "pxr"), (".glb", "pygltflib")])
def test_the_capsule_rig_from_usd_and_gltf_builds_the_same_problem(tmp_path, cache, suffix,
                                                                   extra):
    pytest.importorskip(extra)
    from torchfit.mesh import load_animation
    from torchfit.mesh.rig import blend, distance_weights, segment_distances

    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    animation = load_animation(folder)
    skeleton = animation.skeleton
    skeleton.weights = distance_weights(segment_distances(
        animation.rest_vertices, skeleton.heads, skeleton.tails), 0.06)
    path = tmp_path / f"capsule{suffix}"
    if suffix == ".usda":
        from torchfit.mesh.formats.usd.writer import write_skinned_usd as write
    else:
        from torchfit.mesh.formats.gltf.writer import write_skinned_gltf as write
    write(path, animation.rest_vertices, animation.faces, skeleton)
    problem = problem_for(path, cache)
    read = problem.animation
    assert read.n_frames == 3 and read.skeleton.names == ["lower", "upper"]
    assert np.abs(read.frames - blend(animation.rest_vertices, skeleton.weights,
                                      skeleton.transforms)).max() < 1e-6
    assert problem.model.n_cells > 0 and problem.data.numel() == 3 * read.n_vertices * 3
