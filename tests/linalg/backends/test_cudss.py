"""The ``cudss`` backend: its error paths everywhere, its solves where CUDA and nvmath-python
(cuDSS) are present (skipped otherwise: CI has no GPU)."""
from __future__ import annotations

import pytest
import torch

import torchfit.linalg.backends.cudss as cudss_module
from torchfit.linalg import (BackendDeviceError, CudssBackend, CudssUnavailableError,
                             SingularMatrixError,
                             SparsePattern, counting, default_backend, get_backend)
from torchfit.linalg.backends.cudss import gpu_memory_error
from torchfit.mesh import box_tetrahedra
from torchfit.problems import build_problem
from torchfit.problems import ProblemConfigError

from helpers.linear_system import gradients, linear_equilibrium

HAVE_CUDSS = cudss_module.cudss_available()
needs_cudss = pytest.mark.skipif(not HAVE_CUDSS, reason="needs CUDA and nvmath-python (cuDSS)")


@pytest.fixture
def no_nvmath(monkeypatch):
    """A process where nvmath-python is not importable (whatever this one has)."""
    monkeypatch.setattr(cudss_module, "_NVMATH", None)
    monkeypatch.setattr(cudss_module, "_NVMATH_ERROR", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    import builtins
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name.startswith("nvmath"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    yield
    monkeypatch.setattr(cudss_module, "_NVMATH", None)
    monkeypatch.setattr(cudss_module, "_NVMATH_ERROR", None)


def test_cudss_without_nvmath_is_one_line_naming_the_extra(no_nvmath):
    with pytest.raises(CudssUnavailableError) as info:
        get_backend("cudss")
    message = str(info.value)
    assert "\n" not in message
    assert "pip install 'torchfit[cuda]'" in message and "backend='cg'" in message
    # the default on CUDA then falls back to cg, never to a backend that cannot run there
    assert default_backend(3, "cuda") == "cg"
    assert default_backend(3, "cpu") in ("scipy", "pardiso")


def test_cudss_without_cuda_says_so(monkeypatch):
    monkeypatch.setattr(cudss_module, "_NVMATH", None)
    monkeypatch.setattr(cudss_module, "_NVMATH_ERROR", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(CudssUnavailableError, match="no CUDA device"):
        get_backend("cudss")
    monkeypatch.setattr(cudss_module, "_NVMATH_ERROR", None)


@pytest.mark.parametrize("name", ["scipy", "banded"])
def test_cpu_backend_refuses_cuda_tensors_in_one_line(name):
    """A CPU-only backend given tensors on another device names the device and the
    backends that run there (a meta tensor stands in for a CUDA one on a CPU machine)."""
    pattern = SparsePattern([0, 1], [0, 1], (2, 2))
    values = torch.ones(2, dtype=torch.float64, device="meta")
    with pytest.raises(BackendDeviceError) as info:
        get_backend(name).factorize(pattern, values, True)
    message = str(info.value)
    assert "\n" not in message and "runs on the CPU" in message and "meta" in message
    assert "cudss" in message and "torchfit[cuda]" in message


def test_gpu_out_of_memory_names_the_size_and_what_to_lower():
    err = gpu_memory_error("the cuDSS factorisation",
                           "a 1,030,000 x 1,030,000 sparse matrix with 80,000,000 stored entries",
                           torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate "
                                                       "20 GiB\nmore text"))
    message = str(err)
    assert "\n" not in message and isinstance(err, MemoryError)
    assert "1,030,000 x 1,030,000" in message and "lower the problem size" in message
    assert "problem.backend=cg" in message and "Tried to allocate 20 GiB" in message


# -- problem settings ---------------------------------------------------------------------------
def one_line_error(overrides: dict) -> str:
    with pytest.raises(ProblemConfigError) as info:
        build_problem("spring1d", {"n": 8, **overrides})
    message = str(info.value)
    assert "\n" not in message, message
    return message


def test_settings_cudss_on_cpu_and_cpu_backend_on_cuda_are_refused(monkeypatch):
    message = one_line_error({"backend": "cudss"})
    assert message.startswith("problem.backend=cudss: runs on CUDA only")
    # pretend a GPU is there: a CPU-only backend on it is refused, naming cudss/auto/cg
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    message = one_line_error({"device": "cuda", "backend": "scipy"})
    assert message.startswith("problem.backend=scipy: runs on the CPU only")
    assert "cudss" in message and "auto" in message and "cg" in message


def test_settings_cudss_without_nvmath_names_the_extra(no_nvmath, monkeypatch):
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    message = one_line_error({"device": "cuda", "backend": "cudss"})
    assert message.startswith("problem.backend=cudss: needs nvmath-python with cuDSS")
    assert "pip install 'torchfit[cuda]'" in message


def test_settings_cuda_without_cuda_says_so(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    message = one_line_error({"device": "cuda", "backend": "auto"})
    assert message.startswith("problem.device=cuda: ") and "has no CUDA here" in message


# -- on a GPU ---------------------------------------------------------------------------------
def elastic_system(device: str, cells=(4, 3, 3)):
    """The free-free linear-elastic stiffness of a tet box (z = 0 fixed), on ``device``."""
    from torchfit.physics.elasticity import SimplicialElasticity
    mesh = box_tetrahedra(*cells, (1.0, 1.0, 1.0))
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "linear", nu=0.3, device=device)
    g = torch.Generator().manual_seed(0)
    E = torch.exp(torch.randn(model.n_cells, dtype=torch.float64, generator=g)).to(device)
    values = model.tangent_pattern.assemble(model.tangent_values(model.rest.points.reshape(1, -1), E))[0]
    free = torch.nonzero(model.rest.points[:, 2] > 1e-12).reshape(-1)
    free_dofs = (free[:, None] * 3 + torch.arange(3, device=free.device)).reshape(-1)
    sub, slots = model.tangent_pattern.submatrix(free_dofs, free_dofs)
    return sub, values[slots.to(values.device)]


@needs_cudss
def test_cudss_solves_match_scipy_and_reuse_the_plan():
    pattern, values = elastic_system("cuda")
    n = pattern.shape[0]
    g = torch.Generator().manual_seed(1)
    rhs = torch.randn(n, 11, dtype=torch.float64, generator=g)
    reference = get_backend("scipy").factorize(pattern, values.cpu(), True).solve(rhs)
    backend = get_backend("cudss")
    with counting() as c:
        factor = backend.factorize(pattern, values, True)
        x = factor.solve(rhs.cuda())                  # 11 columns: two blocks of 8
        x1 = factor.solve(rhs[:, 0].cuda())
    assert (c.factorizations, c.solves, c.rhs_columns) == (1, 2, 12)
    assert torch.allclose(x.cpu(), reference, rtol=1e-10, atol=1e-12)
    assert torch.allclose(x1.cpu(), reference[:, 0], rtol=1e-10, atol=1e-12)
    plan = backend.plan(pattern, "spd", values.device, values.dtype)
    assert plan.analyses == 1
    del factor
    import gc
    gc.collect()
    # a new parameter vector: the same slot, no new plan; values updated in place
    factor = backend.factorize(pattern, 2.0 * values, True)
    assert plan.analyses == 1
    assert torch.allclose(factor.solve(rhs.cuda()).cpu(), reference / 2.0, rtol=1e-10, atol=1e-12)


@needs_cudss
def test_cudss_differentiable_solve_matches_cpu_and_refuses_non_spd():
    """The differentiable linear solve (a linear equilibrium on the stiffness matrix): the
    solution and its gradients on the GPU are those of SuperLU on the CPU."""
    pattern, values = elastic_system("cuda", cells=(3, 3, 2))
    n = pattern.shape[0]
    out = {}
    for device, backend in (("cpu", "scipy"), ("cuda", "cudss")):
        eq, shift, fixed = linear_equilibrium(pattern, values.to(device), backend)
        x = eq(shift, fixed)
        out[device] = (x.detach().cpu(), *(g.cpu() for g in gradients(eq, shift, fixed)))
    for a, b in zip(out["cpu"], out["cuda"]):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12)
    indefinite = values.clone()
    diagonal = pattern.row_indices.to(values.device) == pattern.col_indices.to(values.device)
    indefinite[diagonal] *= -1.0
    with pytest.raises(SingularMatrixError, match="not positive definite"):
        CudssBackend(indefinite=False).factorize(pattern, indefinite, True)
    # by default an indefinite symmetric matrix (a Newton tangent) is factorised as such
    factor = get_backend("cudss").factorize(pattern, indefinite, True)
    assert factor.info["kind"] == "symmetric"
    dense = torch.from_numpy(pattern.to_scipy(indefinite).toarray())
    b = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    assert torch.allclose(factor.solve(b.cuda()).cpu(), torch.linalg.solve(dense, b),
                          rtol=1e-8, atol=1e-10)


@needs_cudss
@pytest.mark.parametrize("material", ["corotated", "stable_neo_hookean"])
def test_tet_box_nonlinear_on_cuda_matches_the_cpu(material):
    """The issue's acceptance on a small box: 4 frames, forward and gradient, CUDA + cuDSS
    against CPU + SuperLU to 1e-10."""
    from torchfit.physics import NewtonOptions
    from torchfit.physics.elasticity import QuasistaticElasticity, SimplicialElasticity
    mesh = box_tetrahedra(3, 3, 4, (1.0, 1.0, 1.0))
    results = {}
    for device, backend in (("cpu", "scipy"), ("cuda", "cudss")):
        model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                     material, nu=0.3, device=device)
        X = model.rest.points
        bottom = torch.nonzero(X[:, 2] <= 1e-12).reshape(-1)
        top = torch.nonzero(X[:, 2] >= 1.0 - 1e-12).reshape(-1)
        qs = QuasistaticElasticity(model, torch.cat([bottom, top]).cpu(), backend=backend,
                                   newton=NewtonOptions(rtol=1e-13, atol=1e-14))
        shifts = torch.tensor([[0.05, 0.0, -0.2], [0.0, 0.1, -0.1], [0.0, 0.0, 0.1],
                               [0.1, 0.1, 0.0]], dtype=torch.float64, device=device)
        positions = [torch.cat([X[bottom], X[top] + shift]) for shift in shifts]
        E = torch.ones(model.n_cells, dtype=torch.float64, device=device, requires_grad=True)
        x = qs(E, positions)
        (grad,) = torch.autograd.grad((x * x).sum(), E)
        results[device] = (x.detach().cpu(), grad.cpu())
    assert float((results["cpu"][0] - results["cuda"][0]).abs().max()) < 1e-10
    assert torch.allclose(results["cpu"][1], results["cuda"][1], rtol=1e-8, atol=1e-10)


def test_cg_refuses_a_matrix_that_is_not_positive_definite_in_one_line():
    """Positive diagonal (passes the cheap check), but indefinite: CG meets negative
    curvature and says so instead of returning garbage."""
    pattern = SparsePattern([0, 0, 1, 1], [0, 1, 0, 1], (2, 2))
    values = torch.tensor([1.0, 2.0, 2.0, 1.0], dtype=torch.float64)     # eigenvalues 3, -1
    factor = get_backend("cg").factorize(pattern, values, True)
    with pytest.raises(SingularMatrixError) as info:
        factor.solve(torch.tensor([1.0, -0.5], dtype=torch.float64))
    assert "\n" not in str(info.value) and "positive definite" in str(info.value)
    # an SPD matrix still solves
    spd = torch.tensor([2.0, 0.5, 0.5, 1.0], dtype=torch.float64)
    x = get_backend("cg").factorize(pattern, spd, True).solve(torch.tensor([1.0, 2.0],
                                                                           dtype=torch.float64))
    assert torch.allclose(x, torch.linalg.solve(torch.tensor([[2.0, 0.5], [0.5, 1.0]],
                                                             dtype=torch.float64),
                                                torch.tensor([1.0, 2.0], dtype=torch.float64)))


def test_equilibrium_out_of_gpu_memory_is_one_line_with_the_size(monkeypatch):
    """CUDA's allocator error inside a solve becomes one line naming frames, dofs and what
    to lower (simulated: CI has no GPU to exhaust)."""
    from torchfit.linalg.backends.cudss import GpuMemoryError
    from helpers.tetbox import clamped_box
    _, qs, _, _ = clamped_box((2, 2, 2), (1.0, 1.0, 1.0), "linear")
    eq = qs.equilibrium

    def exhausted(*args, **kwargs):
        raise torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 30.00 GiB")

    monkeypatch.setattr(eq.solver, "solve", exhausted)
    values = torch.zeros(3, eq.n_fixed, dtype=torch.float64)
    with pytest.raises(GpuMemoryError) as info:
        eq(torch.ones(qs.model.n_cells, dtype=torch.float64), values)
    message = str(info.value)
    assert "\n" not in message and "3 frame(s)" in message
    assert f"{eq.free_dofs.numel():,} free dofs" in message and "Tried to allocate 30.00 GiB" in message
    assert "lower the problem size" in message
