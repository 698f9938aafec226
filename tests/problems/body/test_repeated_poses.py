"""Frames that repeat a pose: found once, simulated once, every frame's residual its own."""
import pytest
import torch

from torchfit.linalg import counting
from torchfit.problems import build_problem
from torchfit.problems.body.repeated_poses import distinct_poses

from helpers.capsule_animation import write_capsule


def test_distinct_poses_to_the_tolerance():
    base = torch.rand(3, 5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    frames = torch.stack([base[0], base[1], base[0] + 1e-12, base[2], base[1]])
    poses, pose_of_frame = distinct_poses(frames)
    assert poses.tolist() == [0, 1, 3] and pose_of_frame.tolist() == [0, 1, 0, 2, 1]
    assert distinct_poses(base) is None                       # nothing repeats
    assert distinct_poses(frames, tolerance=0.0)[1].tolist() == [0, 1, 2, 3, 1]


def capsule_problem(tmp_path, angles):
    folder = write_capsule(tmp_path / "capsule", angles=angles)
    return build_problem("animation", {"path": str(folder), "tet_edge_length": 0.1,
                                       "grid": [2, 2, 2], "cache_dir": str(tmp_path)})


@pytest.mark.slow       # about 50 s on the loaded 2-core machine (a tet mesh, four solves)
def test_repeated_pose_simulated_once_and_weighted_as_the_data(tmp_path):
    # a bend played forward and back: frames 3 and 4 repeat frames 1 and 0
    problem = capsule_problem(tmp_path, (0.0, 20.0, 40.0, 20.0, 0.0))
    poses, pose_of_frame = problem.poses.repeated_poses
    assert poses.tolist() == [0, 1, 2] and pose_of_frame.tolist() == [0, 1, 2, 1, 0]
    theta = problem.theta0 + 0.1 * torch.sin(torch.arange(problem.theta0.numel(),
                                                          dtype=problem.theta0.dtype))
    E = problem.parameterization(theta)
    with counting() as count:
        x = problem.simulate(E)
    assert x.shape[0] == 5 and torch.equal(x[3], x[1]) and torch.equal(x[4], x[0])
    # three poses solved: Newton's factorisations are those of three frames (the cold
    # start's one each, and a frame that finishes at a saddle with the exact tangent may
    # take one more: 20 against 16 + 3 on one CI mesh), never those of five
    newton = sum(problem.poses.quasistatic.last_newton_iterations)
    assert newton + 3 <= count.factorizations <= newton + 6
    assert len(problem.poses.quasistatic.last_newton_iterations) == 3
    # the dense Jacobian: bit for bit the one of every frame simulated, repeated rows equal
    J = problem.forward_jacobian(theta)
    assert float(J.abs().max()) > 1e-5
    rows = J.reshape(5, -1, theta.numel())
    assert torch.equal(rows[3], rows[1]) and torch.equal(rows[4], rows[0])
    shared, problem.poses.repeated_poses = problem.poses.repeated_poses, None
    problem.poses.quasistatic.equilibrium.clear_cache()
    x_all = problem.simulate(E)
    assert len(problem.poses.quasistatic.last_newton_iterations) == 5
    assert torch.allclose(x_all, x, rtol=0, atol=1e-9)
    assert torch.allclose(problem.forward_jacobian(theta), J, rtol=1e-7, atol=1e-12)
    problem.poses.repeated_poses = shared
    # the gradient of the misfit counts a repeated frame as often as the data hold it
    t = theta.clone().requires_grad_(True)
    w = torch.rand(J.shape[0], dtype=theta.dtype, generator=torch.Generator().manual_seed(1))
    (problem.observe(problem.simulate(problem.parameterization(t))) @ w).backward()
    assert torch.allclose(t.grad, J.T @ w, rtol=1e-7, atol=1e-12)
