"""scripts/blender/torchfit_blender/command.py: the panel's settings as torchfit command lines."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from torchfit_blender.command import (CommandError, FitSettings, JobFolder, file_frames,
                                      find_interpreter, fit_command, python_environment,
                                      simulate_command)

REPO = Path(__file__).resolve().parents[3]


def test_a_fit_command_carries_every_setting_and_resume_adds_only_resume(tmp_path):
    job = JobFolder(tmp_path / "job")
    settings = FitSettings(frame_start=10, frame_end=20, held_out=(15, 12), model="linear",
                           grid_nodes=64, iterations=7, dynamic=True, tet_edge_length=0.08,
                           threads=1, init_field="/p/painted.usda")
    command = fit_command(settings, job, REPO, "/venv/bin/python")
    assert command[:2] == ["/venv/bin/python", str(REPO / "experiments" / "fit.py")]
    assert command[2:] == [f"hydra.run.dir={tmp_path / 'job' / 'run'}", "problem=animation",
                           f"problem.path={tmp_path / 'job' / 'rig.usda'}",
                           "problem.model=linear", "problem.grid_nodes=64",
                           "problem.tet_edge_length=0.08", "solver.max_iter=7",
                           "problem.dynamic=true", "problem.validation_frames=[2,5]",
                           "problem.init_field=/p/painted.usda", "threads=1"]
    resumed = fit_command(settings, job, REPO, "/venv/bin/python", resume=True)
    assert resumed == command + ["resume=true"]
    plain = fit_command(FitSettings(frame_start=1, frame_end=3), job, REPO, "py")
    assert "problem.dynamic=false" in plain
    assert not any(x.startswith(("problem.validation_frames", "problem.init_field", "threads"))
                   for x in plain)


def test_blender_frames_become_file_frames_and_bad_settings_are_one_line():
    assert file_frames([1, 3], 1, 5) == [0, 2]
    with pytest.raises(CommandError, match="held-out frame 9 is outside the frame range 1-5"):
        file_frames([9], 1, 5)
    with pytest.raises(CommandError, match="frame range 4-4"):
        fit_command(FitSettings(frame_start=4, frame_end=4), JobFolder(Path("j")), REPO, "py")


def test_the_interpreter_is_the_preference_or_the_repositorys_venv(tmp_path):
    assert find_interpreter(REPO, sys.executable) == Path(sys.executable)
    with pytest.raises(CommandError, match="interpreter .*nothing/python not found"):
        find_interpreter(REPO, str(tmp_path / "nothing" / "python"))
    with pytest.raises(CommandError, match="has no experiments/fit.py"):
        find_interpreter(tmp_path)
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments" / "fit.py").write_text("")
    venv = tmp_path / ".venv" / "bin"
    venv.mkdir(parents=True)
    (venv / "python").write_text("#!/bin/sh\n")
    (venv / "python").chmod(0o755)
    assert find_interpreter(tmp_path) == venv / "python"


def test_simulate_command_and_an_environment_without_blenders_python(monkeypatch):
    command = simulate_command("/r/fit", "/r/walk.usda", "/r/sim", REPO, "py")
    assert command == ["py", str(REPO / "experiments" / "simulate.py"), "hydra.run.dir=/r/sim",
                       "run=/r/fit", "problem.path=/r/walk.usda", "problem.frames=null"]
    assert simulate_command("f", "a", "o", REPO, "py", dynamic=False)[-1] == \
        "problem.dynamic=false"
    bundled = "/v/site-packages/bpy/4.5/python/lib/python3.11/site-packages"
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([bundled, "/work/tree"]))
    monkeypatch.setenv("PYTHONHOME", "/blender/python")
    env = python_environment()
    assert env["PYTHONPATH"] == "/work/tree" and "PYTHONHOME" not in env
