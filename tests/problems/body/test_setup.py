"""A rigged body's set-up (torchfit.problems.body.setup): the rig refused before anything is
built, and every set-up step on the console with its counts and time."""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from helpers.capsule_animation import write_capsule
from helpers.fit_app import run_fit_app
from helpers.rigged_tube import write_tube
from torchfit import build_problem
from torchfit.problems import ProblemConfigError
from torchfit.problems.body import setup as body_setup
from torchfit.problems.body import problem as body_problem

DATA = Path(__file__).resolve().parents[2] / "data"


def transpose_bones(folder: Path) -> None:
    with np.load(folder / "skeleton.npz") as data:
        bones = {k: data[k] for k in data.files}
    bones["transforms"] = np.concatenate([np.swapaxes(bones["transforms"][..., :3], -1, -2),
                                          bones["transforms"][..., 3:]], axis=-1)
    np.savez(folder / "skeleton.npz", **bones)


def test_a_transposed_rig_is_refused_before_anything_is_built(tmp_path):
    folder = write_tube(tmp_path / "tube", "y")
    transpose_bones(folder)
    cache = tmp_path / "cache"
    with pytest.raises(ProblemConfigError) as info:
        build_problem("animation", {"path": str(folder), "cache_dir": str(cache)})
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{folder / 'animation.yaml'}: skinning the rest")
    assert "frames 1-4 (4 of 5) on bones tip" in text and "likely cause: transposed A" in text
    assert text.endswith("(problem.rig_check=false fits it anyway; problem.rig_tolerance sets "
                         "the tolerance)")
    assert not cache.exists()                                  # no tet mesh was made


def test_rig_check_false_and_the_tolerance_let_it_through(tmp_path, monkeypatch):
    folder = write_tube(tmp_path / "tube", "x")
    transpose_bones(folder)

    class Built(Exception):
        pass

    def stop(cfg, animation, motion=None, kept=None):
        raise Built(animation.n_frames)

    # the rig check passed when the body goes on to tetrahedralise its surface
    monkeypatch.setattr(body_problem, "tet_mesh", stop)
    for settings in ({"rig_check": False}, {"rig_tolerance": 3.0}):
        with pytest.raises(Built):
            build_problem("animation", {"path": str(folder), **settings})
    with pytest.raises(ProblemConfigError, match="problem.rig_tolerance=0.0: must be positive"):
        build_problem("animation", {"path": str(folder), "rig_tolerance": 0.0})


def test_the_app_refuses_mm_frames_in_one_line_and_writes_nothing(tmp_path):
    folder = write_tube(tmp_path / "tube", "x")
    with np.load(folder / "frames.npz") as data:
        np.savez(folder / "frames.npz", frames=data["frames"] * 1000.0)
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=animation", f"problem.path={folder}",
                       f"problem.cache_dir={tmp_path / 'cache'}")
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2 and len(errors) == 1, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert "frames 0-4 (5 of 5) are 1000 times the rest surface's size" in errors[0]
    assert "frames in mm against a rest in m?" in errors[0]
    assert not run.exists() and not (tmp_path / "cache").exists()


def test_every_set_up_step_is_on_the_console_with_its_counts(tmp_path, caplog, monkeypatch):
    """The capsule on its kept mesh (tests/data/capsule_mesh): reading, the rig check, the
    tet count and cache file, embedding, the driven vertices, the first simulation (with a
    line per Newton iteration here)."""
    monkeypatch.setattr(body_setup, "FIRST_SIMULATION_BEAT_S", 0.0)
    shutil.copytree(DATA / "capsule_mesh", tmp_path / "cache")
    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    caplog.set_level(logging.INFO, logger="torchfit.setup")
    problem = build_problem("animation", {"path": str(folder), "cache_dir": str(tmp_path / "cache"),
                                          "tet_edge_length": 0.12, "grid": [2, 2, 3],
                                          "target": "synthetic"})
    lines = [r.getMessage() for r in caplog.records if r.name == "torchfit.setup"]
    beats = [line for line in lines if "Newton iteration" in line]
    lines = [line for line in lines if line not in beats]
    assert beats and all(b.startswith(f"first simulation of 3 frames ({problem.model.n_cells:,} "
                                      "tetrahedra, corotated): Newton iteration ") for b in beats)
    assert ", 3 of 3 frames converged, " in beats[-1]
    n_tets, n_points = problem.model.n_cells, problem.model.n_vertices
    V = problem.animation.n_vertices
    expected = [
        f"reading the animation {folder} ...",
        f"reading the animation {folder}: {V:,} surface vertices, 3 frames, a skeleton of 2 "
        "bones (weights from distance), ",
        "checking the rig against the frames ...",
        "checking the rig against the frames: frame sizes ",
        "tetrahedralising a surface of ",
        f"tetrahedralising a surface of {len(problem.animation.faces):,} faces (pytetwild: edge "
        f"length 0.12 of the diagonal, envelope 0.001): {n_tets:,} tetrahedra, {n_points:,} "
        f"vertices, read from the cache {problem.tet.path}, ",
        f"embedding {V:,} surface vertices in {n_tets:,} tetrahedra ...",
        f"embedding {V:,} surface vertices in {n_tets:,} tetrahedra: done in ",
        f"attaching the rig to {n_points:,} tetrahedron vertices in 3 frames ...",
        f"attaching the rig to {n_points:,} tetrahedron vertices in 3 frames: "
        f"{len(problem.dirichlet_vertices):,} driven (prescribed), ",
        "rig: bone ", "rig: bone ",
        f"rig: attach radius {problem.animation.skeleton.attach_radius:.4g} m: authored: the "
        "file's attach radius",
        "rig: weights derived: from each vertex's distance to the bones (reach attach_radius)",
        f"first simulation of 3 frames ({n_tets:,} tetrahedra, corotated) ...",
        f"first simulation of 3 frames ({n_tets:,} tetrahedra, corotated): 3 frames in "
        "equilibrium, ",
    ]
    assert len(lines) == len(expected), lines
    for line, start in zip(lines, expected):
        assert line.startswith(start), (line, start)
    assert "with weights from distance reproduces" in lines[3]    # weights: distance
    bones = problem.rig_description["bones"]
    assert sum(b["driven_vertices"] for b in bones) == len(problem.dirichlet_vertices)
    for line, bone in zip(lines[10:12], bones):
        assert line == (f"rig: bone {bone['name']}: {bone['length_m']:.4g} m, "
                        f"{bone['driven_vertices']:,} driven vertices; length authored: the "
                        "file's bone segment")
    assert problem.rig_report.distance_weights and problem.rig_report.skinning_error < 0.05
    assert problem.rig_report.scale_ratios.shape == (3,)
    assert lines[-1].endswith(" s")


def test_the_app_refuses_a_stage_with_every_joint_at_the_origin_and_writes_nothing(tmp_path):
    pytest.importorskip("pxr")
    from helpers.rigged_tube import write_tube_stage

    stage = write_tube_stage(tmp_path / "origin.usda", at_origin=True)
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=animation", f"problem.path={stage}",
                       f"problem.cache_dir={tmp_path / 'cache'}")
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2 and len(errors) == 1, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert errors[0].startswith(f"error: problem.path={stage}: /Root/Tube: joints base, tip "
                                "coincide (all at (0, 0, 0) m in the rest pose), so their bones "
                                "have no length and hold no flesh; ")
    assert not run.exists() and not (tmp_path / "cache").exists()
