"""torchfit.run.simulating: the summary of a simulation of a fitted material."""
from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.run import FitConfigError, SimulationResult
from torchfit.run.simulating import check_parameters


def test_the_summary_names_the_worst_frame_by_its_animation_number():
    """Issue 50: simulating frames [2, 4, 6] named "worst frame 1" (the index into the
    selection) for the animation's frame 4."""
    problem = types.SimpleNamespace(frame_numbers=lambda: [2, 4, 6],
                                    animation=types.SimpleNamespace(path=Path("/w/shot/x.yaml")),
                                    time=types.SimpleNamespace(in_time=False))
    errors = {"surface_err_mean": np.array([1e-3, 3e-3, 2e-3]),
              "surface_err_max": np.array([2e-3, 5e-3, 4e-3]),
              "inverted_tets": np.array([0, 2, 0])}
    result = SimulationResult(Path("/w/run"), problem, torch.zeros(3, 4, 3), torch.zeros(3, 2, 3),
                              torch.ones(1), errors, [3, 4, 5], [0.1] * 3, 1.5)
    line = result.summary()
    assert "mean surface error 2 mm (worst frame 4: 3 mm)" in line
    assert "12 Newton iterations, 1 frames with inverted tetrahedra" in line
    # in time: the integration's steps (the Newton iterations per frame are not counted)
    problem.time.in_time, problem.integrator = True, types.SimpleNamespace(n_steps=92)
    assert "(worst frame 4: 3 mm), 92 time steps, 1 frames" in result.summary()


@pytest.mark.parametrize("fitted, now, words", [
    (True, False, "was fitted in time (problem.dynamic=true): its parameters are the field and "
                  "the damping; simulate it in time with problem.dynamic=true"),
    (False, True, "was fitted frame by frame (quasistatic) and holds no damping"),
])
def test_a_run_fitted_in_time_or_not_is_said_so(fitted, now, words):
    """Issue 50: a run fitted in time simulated with problem.dynamic=false got a parameter
    count pointing at problem.grid."""
    run = types.SimpleNamespace(directory=Path("/w/run"), settings={"dynamic": fitted})
    body = types.SimpleNamespace(cfg=types.SimpleNamespace(dynamic=now))
    with pytest.raises(FitConfigError, match=words.replace("(", r"\(").replace(")", r"\)")):
        check_parameters(run, body)
