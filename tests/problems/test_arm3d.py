"""problem=arm3d (PROBLEMS.md): the procedural arm through the animation path.

Fast tests use a coarse arm (about 1-2k tetrahedra) and a few frames; the acceptance runs of
the issue at full size are in scripts/bench_arm3d.py and the README's figures.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfit import build_problem, fit, verify
from torchfit.verification import format_report
from torchfit.mesh import signed_volumes
from torchfit.mesh.animation import load_animation
from torchfit.problems import ProblemConfigError

COARSE = {"tet_edge_length": 0.1, "grid": [3, 3, 4]}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("arm-cache"))


def arm(cache, **settings):
    return build_problem("arm3d", {"cache_dir": cache, **COARSE, **settings})


def test_arm_goes_through_the_user_animation_format(cache):
    problem = arm(cache, frames=[0, 5])
    animation = load_animation(problem.animation.path)     # the folder the arm wrote
    assert animation.n_frames == 48 and animation.skeleton.n_bones == 2
    assert problem.n_frames == 2 and problem.frame_names()[1].startswith("frame 5: elbow +55")
    # attached vertices lie within attach_radius of a bone, the rest are free
    assert 0 < len(problem.dirichlet_vertices) < problem.model.n_vertices
    assert set(np.unique(problem.tet_regions)) == {0, 1, 2}
    again = arm(cache, frames=[0, 5])
    assert again.tet.from_cache and np.array_equal(again.tet.cells, problem.tet.cells)


def test_forward_jacobian_matches_jvps(cache):
    problem = arm(cache, frames=[0, 3], model="corotated")
    theta = problem.theta0 + 0.1 * torch.randn(problem.theta0.shape, dtype=torch.float64,
                                               generator=torch.Generator().manual_seed(1))
    J = problem.forward_jacobian(theta)
    lin = problem.residual().linearize(theta)
    for j in (0, 7, problem.parameterization.n_params - 1):
        e = torch.zeros_like(theta)
        e[j] = 1.0
        column = lin.jvp(e)
        assert torch.allclose(J[:, j], column, rtol=1e-9, atol=1e-12 * column.abs().max())


@pytest.mark.parametrize("model", ["linear", pytest.param("corotated", marks=pytest.mark.slow),
                                   pytest.param("stable_neo_hookean", marks=pytest.mark.slow)])
def test_verify_passes_for_each_model(cache, tmp_path, model):
    problem = arm(cache, frames=[0, 3], model=model)
    report = verify(problem, run_dir=tmp_path)
    # the checks: Taylor rate and dot product; the central difference is limited by
    # Newton's tolerance (rtol 1e-10 per frame): its default tolerance follows it (2.2e-5)
    assert abs(report.taylor.rate - 2.0) <= 0.05, format_report(report)
    assert report.dot.rel_error <= 1e-10, format_report(report)
    assert report.fd_tol == pytest.approx(100 * 1e-10 ** (2 / 3))
    assert report.fd.rel_error <= 1e-5 and report.passed, format_report(report)


@pytest.mark.slow
def test_linear_flattens_more_than_corotated_at_full_bend(cache):
    """At 120 degrees the linear model flattens the rotated forearm (its linearised strain
    of a rotation is not zero); the corotated one keeps its volume. The elbow region's own
    figure depends on how pytetwild's mesh folds there (default resolution, two meshes:
    linear -30 % and -28 %, corotated -16 % and -15 %; at 0.06 anywhere from -9 % to -31 %
    for linear), so it is reported, and the forearm is what this test holds to."""
    problem = arm(cache, frames=[11], tet_edge_length=0.06)
    E = problem.field(problem.theta0)
    forearm = problem.mesh.centroids()[:, 2] > 0.35
    cells = problem.mesh.cells[forearm]
    rest = float(signed_volumes(problem.mesh.points, cells).sum())
    change = {}
    for model in ("linear", "corotated"):
        x = problem.simulate_model(model, E)
        change[model] = float(signed_volumes(x[0].numpy(), cells).sum()) / rest - 1.0
        assert np.isfinite(problem.joint_volume_change(x)[0])
    assert change["linear"] < -0.3 and abs(change["corotated"]) < 0.05, change


def test_bad_settings_are_one_line(cache):
    with pytest.raises(ProblemConfigError, match="problem.path=/somewhere: is not used by arm3d"):
        build_problem("arm3d", {"path": "/somewhere"})
    with pytest.raises(ProblemConfigError, match="problem.frames.*frame 60 does not exist"):
        arm(cache, frames=[0, 60])
    with pytest.raises(ProblemConfigError, match="problem.noise"):
        arm(cache, noise=1e-4, noise_of_bulge=0.01)


@pytest.mark.slow
def test_synthetic_blocks_are_recovered_on_the_grid(cache):
    problem = arm(cache, frames=[0, 3, 6], target="synthetic", truth="blocks")
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 15, "max_step": 1.0})
    assert result.metrics["k_err_rel_aligned"] <= 1e-3


@pytest.mark.slow
def test_rig_fit_beats_the_homogeneous_material(cache):
    problem = arm(cache, frames=[0, 6, 11])
    result = fit(problem, {"name": "levenberg_marquardt", "max_iter": 6, "max_step": 1.0})
    assert result.metrics["surface_err_reduction"] > 1.0
