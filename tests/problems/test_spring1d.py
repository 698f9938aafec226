import math

import numpy as np
import pytest
import torch

from torchfit.problems import ProblemConfigError, Spring1D, build_problem
from torchfit.problems.spring1d import true_stiffness


def test_reproduces_independent_vectors(vectors_dir):
    data = np.load(vectors_dir / "spring1d_n64.npz")
    problem = Spring1D(gravity=float(data["gravity"]), loads=data["loads"].tolist())
    x = problem.simulate(torch.from_numpy(data["k"]))
    assert x.shape == (3, 65, 1)
    np.testing.assert_allclose(x[..., 0].numpy(), data["positions"], rtol=0, atol=1e-10)


def test_closed_form_positions():
    """Each spring carries the weight of the nodes below it plus the end load."""
    problem = Spring1D(n=10, loads=[0.5])
    k = torch.linspace(50, 150, 10)
    x = problem.simulate(k)[0, :, 0]
    tension = torch.tensor([(10 - i) * 9.81 / 10 + 0.5 for i in range(10)])
    expected = torch.cat([torch.zeros(1), torch.cumsum(0.1 + tension / k, 0)])
    assert torch.allclose(x, expected, atol=1e-12)


def test_truth_is_the_canonical_field():
    k = true_stiffness(64)
    assert (k[16:32] == 400).all() and (k[40:48] == 25).all()
    assert (k[:16] == 100).all() and (k[32:40] == 100).all() and (k[48:] == 100).all()


def test_data_modes_and_noise_level():
    dense = Spring1D()
    assert dense.data.numel() == 3 * 64
    sparse = Spring1D(data="sparse")
    assert sparse.observed_nodes.tolist() == [8, 16, 24, 32, 40, 48, 56, 64]
    noisy = Spring1D(noise=1e-3, seed=3)
    assert noisy.noise_level == pytest.approx(1e-3 * math.sqrt(3 * 64))
    again = Spring1D(noise=1e-3, seed=3)
    assert torch.equal(noisy.data, again.data)           # seeded
    assert not torch.equal(noisy.data, Spring1D(noise=1e-3, seed=4).data)
    assert dense.noise_level is None


def test_metrics_are_zero_at_truth_and_not_scale_free():
    problem = Spring1D()
    metrics = problem.metrics(problem.parameterization.inverse(problem.field_true))
    assert metrics["k_err_rel"] < 1e-14 and metrics["u_err_inf"] < 1e-12
    assert metrics["misfit"] < 1e-12
    assert "k_err_rel_aligned" not in metrics           # gravity fixes the scale
    m0 = problem.metrics(problem.theta0)
    expected = float((problem.field_true - 100).norm() / problem.field_true.norm())
    assert m0["k_err_rel"] == pytest.approx(expected)


@pytest.mark.parametrize("overrides, match", [
    ({"n": 0}, "problem.n"),
    ({"noise": -1.0}, "problem.noise"),
    ({"data": "everything"}, "dense"),
    ({"data": "sparse", "sparse_stride": 100}, "larger than the chain"),
    ({"fixed_nodes": []}, "singular"),
    ({"loads": []}, "load case"),
])
def test_bad_settings_are_clear_errors(overrides, match):
    with pytest.raises(ProblemConfigError, match=match):
        Spring1D(**overrides)


def test_wrong_parameter_shape_is_named():
    problem = Spring1D(n=8)
    with pytest.raises(ProblemConfigError, match=r"shape \(8,\)"):
        problem.simulate(torch.ones(7))
    with pytest.raises(ValueError, match=r"shape \(8,\)"):
        problem.forward(torch.ones(9))


def test_nan_targets_name_frame_and_node(tmp_path):
    positions = Spring1D(n=4).x_true[..., 0].numpy().copy()
    positions[2, 3] = np.nan
    path = tmp_path / "targets.npy"
    np.save(path, positions)
    with pytest.raises(ProblemConfigError, match="frame 2, node 3"):
        Spring1D(n=4, targets=str(path))
    np.save(path, positions[:, :4])
    with pytest.raises(ProblemConfigError, match="shape"):
        Spring1D(n=4, targets=str(path))


def test_user_targets_fit_without_truth(tmp_path):
    reference = Spring1D(n=4)
    path = tmp_path / "targets.npy"
    np.save(path, reference.x_true[..., 0].numpy())
    problem = Spring1D(n=4, targets=str(path))
    assert problem.field_true is None
    assert torch.allclose(problem.data, reference.data)
    assert set(problem.metrics(problem.theta0)) == {"misfit"}


def test_registry_rejects_unknown_names_and_settings():
    with pytest.raises(ProblemConfigError, match="spring1d"):
        build_problem("spring2d")
    with pytest.raises(ProblemConfigError, match="bogus"):
        build_problem("spring1d", {"bogus": 1})


def test_cg_backend_agrees_with_direct_solver():
    direct, iterative = Spring1D(n=32), Spring1D(n=32, backend="cg")
    assert torch.allclose(direct.x_true, iterative.x_true, atol=1e-11)
    theta = direct.theta0 + 0.1 * torch.randn(32)
    v, w = torch.randn(32), torch.randn(direct.data.numel())
    lin_d, lin_i = direct.residual().linearize(theta), iterative.residual().linearize(theta)
    assert torch.allclose(lin_d.jvp(v), lin_i.jvp(v), atol=1e-10)
    assert torch.allclose(lin_d.vjp(w), lin_i.vjp(w), atol=1e-8)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_path_matches_cpu():
    cpu, gpu = Spring1D(n=32), Spring1D(n=32, backend="cg", device="cuda")
    assert gpu.x_true.device.type == "cuda"
    assert torch.allclose(cpu.x_true, gpu.x_true.cpu(), atol=1e-10)
    lin = gpu.residual().linearize(gpu.theta0)
    assert lin.vjp(lin.r).device.type == "cuda"
