"""The ``cudss`` backend: its error paths everywhere; its logic (the device made current in
every calling thread, one analysis per pattern, factors re-made in their slot, blocks of
right-hand sides) with a stand-in for nvmath everywhere (``helpers/fake_nvmath.py``); its
solves where CUDA and nvmath-python (cuDSS) are present (skipped otherwise: CI has no GPU)."""
from __future__ import annotations

import gc
import threading

import pytest
import torch

import torchfit.linalg.backends.cudss as cudss_module
from torchfit.linalg import (BackendDeviceError, CudssBackend, CudssUnavailableError,
                             SingularMatrixError,
                             SparsePattern, counting, default_backend, get_backend)
from torchfit.linalg import GpuMemoryError
from torchfit.linalg.backends.cudss import (MAX_RHS_BLOCK, NvmathRuntime, gpu_memory_error,
                                            rhs_block_for)
from torchfit.mesh import box_tetrahedra
from torchfit.problems import build_problem
from torchfit.problems import ProblemConfigError

from helpers.fake_nvmath import FakeCuda, FakeDevice, NotCurrentError
from helpers.grid_matrices import grid_laplacian
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


# -- with a stand-in for nvmath (every machine) -------------------------------------------------
def laplacian(nx: int = 10, ny: int = 8, seed: int = 0):
    pattern, values = grid_laplacian(nx, ny, seed=seed)
    return pattern, values.to(torch.float64)


def in_thread(fn):
    """``fn()`` run on a new thread (as autograd runs a CUDA backward): its result and the
    thread's id; its exception is raised here."""
    out: dict = {}

    def run():
        out["thread"] = threading.get_ident()
        try:
            out["value"] = fn()
        except BaseException as err:  # noqa: BLE001 - re-raised in the caller
            out["error"] = err

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    if "error" in out:
        raise out["error"]
    return out.get("value"), out["thread"]


def backward_on_another_thread(eq, shift, fixed):
    """Gradients of ``||x*||^2`` (as :func:`gradients`), the forward on this thread and the
    backward on a new one, as autograd runs a CUDA backward: ``(gradients, its thread)``."""
    leaves = (shift.clone().requires_grad_(True), fixed.clone().requires_grad_(True))
    loss = eq(*leaves).square().sum()
    return in_thread(lambda: torch.autograd.grad(loss, leaves))


def test_every_nvmath_call_makes_the_device_current_in_the_calling_thread():
    """The failure measured on the H200: autograd ran the backward's solve on its own
    thread, where cuda.core had no current device. The stand-in refuses such a call as
    cuda.core does; the backend makes the device current before each call, on whatever
    thread calls (the backward's, a finaliser's)."""
    fake = FakeCuda()
    pattern, values = laplacian()
    reference = gradients(*linear_equilibrium(pattern, values, "scipy"))
    kept = [linear_equilibrium(pattern, values, CudssBackend(runtime=fake))]
    grads, backward_thread = backward_on_another_thread(*kept[0])
    for got, want in zip(grads, reference):
        assert torch.allclose(got, want, rtol=1e-12, atol=1e-14)
    assert backward_thread != threading.get_ident()
    assert fake.threads("solve") == {threading.get_ident(), backward_thread}
    assert (backward_thread, torch.device("cpu")) in fake.made_current
    # the plan's solver is freed by the thread that drops the last reference to the pattern
    _, gc_thread = in_thread(lambda: (kept.clear(), gc.collect()))
    assert fake.count("free") == fake.count("plan") == 1 and fake.threads("free") == {gc_thread}


def test_the_stand_in_refuses_a_thread_without_a_current_device():
    """The negative control: a runtime whose ``make_current`` does nothing fails as nvmath
    did on the GPU (so the test above can fail)."""
    pattern, values = laplacian()
    factor = CudssBackend(runtime=FakeCuda(make_current_works=False)).factorize(
        pattern, values, True)
    with pytest.raises(NotCurrentError, match="set_current"):
        factor.solve(torch.ones(pattern.shape[0], dtype=torch.float64))


def test_nvmath_runtime_makes_the_tensors_device_current():
    """``NvmathRuntime.make_current`` is cuda.core's ``Device(index).set_current()`` for the
    factor's device (a torchrun worker's ``cuda:1``), on the calling thread."""
    runtime = NvmathRuntime(advanced=FakeCuda().advanced, device_class=FakeDevice)
    _, thread = in_thread(lambda: runtime.make_current(torch.device("cuda", 1)))
    assert FakeDevice.current[thread] == 1
    runtime.make_current(torch.device("cuda", 0))
    assert FakeDevice.current[threading.get_ident()] == 0


def test_one_analysis_serves_every_factor_of_a_pattern():
    """Three matrices of one pattern, solved in turn: one plan (analysis), each factor
    factorised at its first solve and again when it lost the slot, solutions exact."""
    fake = FakeCuda()
    pattern, values = laplacian()
    backend = CudssBackend(runtime=fake, rhs_block=4)
    rhs = torch.randn(pattern.shape[0], 11, dtype=torch.float64,
                      generator=torch.Generator().manual_seed(1))
    scales = (1.0, 2.0, 5.0)
    reference = get_backend("scipy").factorize(pattern, values, True).solve(rhs)
    with counting() as count:
        factors = [backend.factorize(pattern, s * values, True) for s in scales]
        assert count.factorizations == 0                   # made at the first solve
        first = [f.solve(rhs) for f in factors]            # 3 numeric factorisations
        again = [f.solve(rhs[:, 0]) for f in reversed(factors)]   # 2 made again, 1 resident
    for s, x, x0 in zip(scales, first, reversed(again)):
        assert torch.allclose(x, reference / s, rtol=1e-12, atol=1e-14)
        assert torch.allclose(x0, reference[:, 0] / s, rtol=1e-12, atol=1e-14)
    assert (count.analyses, count.factorizations, count.solves, count.rhs_columns) == \
        (1, 5, 6, 36)
    plan = factors[0].plan
    assert plan.analyses == 1 and plan.refactorizations == 2 and plan.rhs_block == 4
    assert fake.count("plan") == 1 and fake.count("factorize") == 5
    assert fake.count("solve") == 3 * 3 + 3               # 11 columns: 3 blocks of 4
    # a new backend (every equilibrium makes one) shares the pattern's plan
    with counting() as count:
        CudssBackend(runtime=fake, rhs_block=4).factorize(pattern, values, True).solve(rhs)
    assert count.analyses == 0 and fake.count("plan") == 1
    # resident=2: two analyses, two factors kept (fewer made again)
    backend2 = CudssBackend(runtime=fake, rhs_block=4, resident=2)
    with counting() as count:
        factors = [backend2.factorize(pattern, s * values, True) for s in scales[:2]]
        for _ in range(2):
            for f in factors:
                f.solve(rhs[:, 0])
    assert (count.analyses, count.factorizations) == (2, 2)


def test_rhs_block_is_chosen_per_pattern_size():
    assert rhs_block_for(1_000, 8) == MAX_RHS_BLOCK
    assert rhs_block_for(1_550_000, 8) == 5          # a 3M-tetrahedron box: ~64 MiB a call
    assert rhs_block_for(150_000, 8) == 55           # a 300k-tetrahedron body
    assert rhs_block_for(10 ** 9, 8) == 1


def test_stand_in_indefinite_fallback_and_nonsymmetric_solves():
    """A symmetric matrix that is not positive definite is factorised as indefinite (a plan
    of its own, counted) and stays so; with ``indefinite=False`` one line says why. A
    nonsymmetric one gets LU and no transposed solve."""
    fake = FakeCuda()
    pattern, values = elastic_system("cpu", cells=(3, 3, 2))
    n = pattern.shape[0]
    indefinite = values.clone()
    indefinite[pattern.row_indices == pattern.col_indices] *= -1.0
    dense = torch.from_numpy(pattern.to_scipy(indefinite).toarray())
    b = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    with counting() as count:
        factor = CudssBackend(runtime=fake).factorize(pattern, indefinite, True)
        x = factor.solve(b)
        assert factor.info == {"kind": "symmetric", "factorized": True}
        assert torch.allclose(factor.solve(b, transpose=True), x)
    assert torch.allclose(x, torch.linalg.solve(dense, b), rtol=1e-9, atol=1e-11)
    assert count.analyses == 2 and count.factorizations == 1   # the SPD plan, the LDL^T one
    spd = CudssBackend(runtime=fake).plan(pattern, "spd", values.device, values.dtype)
    assert spd.rejected == 1 and factor.plan.kind == "symmetric" and factor.plan.analyses == 1
    with pytest.raises(SingularMatrixError, match="not positive definite") as info:
        CudssBackend(runtime=fake, indefinite=False).factorize(pattern, indefinite, True).solve(b)
    assert "\n" not in str(info.value)
    general = values.clone()
    general[pattern.row_indices < pattern.col_indices] *= 1.1
    factor = CudssBackend(runtime=fake).factorize(pattern, general, False)
    dense = torch.from_numpy(pattern.to_scipy(general).toarray())
    assert torch.allclose(factor.solve(b), torch.linalg.solve(dense, b), rtol=1e-9, atol=1e-11)
    with pytest.raises(NotImplementedError, match="no transposed solve"):
        factor.solve(b, transpose=True)


def test_stand_in_out_of_memory_while_planning_is_one_line():
    fake = FakeCuda()
    pattern, values = laplacian(7, 5)
    fake.fail["plan"] = RuntimeError("cuDSS error: CUDSS_STATUS_ALLOC_FAILED\ndetails")
    with pytest.raises(GpuMemoryError) as info:
        CudssBackend(runtime=fake).factorize(pattern, values, True).solve(
            torch.ones(pattern.shape[0], dtype=torch.float64))
    message = str(info.value)
    assert "\n" not in message and "cuDSS planning" in message and "35 x 35" in message


def four_frame_fit(backend):
    """A 4-frame stable neo-Hookean box whose lower half's modulus ratio (one parameter,
    ``exp(theta)``) is fitted by Levenberg-Marquardt to the positions of ``theta = 0.4``:
    ``(theta, counts)``."""
    from torchfit.solvers import LevenbergMarquardtConfig, ResidualFunction, levenberg_marquardt
    from helpers.tetbox import clamped_box

    model, qs, bottom, top = clamped_box((2, 2, 3), (1.0, 1.0, 1.0), "stable_neo_hookean",
                                         backend, atol=1e-12)
    X = model.rest.points
    shifts = torch.tensor([[0.1, 0.0, -0.25], [0.0, 0.15, -0.1], [0.0, 0.0, 0.2],
                           [0.15, 0.1, 0.05]], dtype=torch.float64)
    positions = torch.stack([torch.cat([X[bottom], X[top] + s]) for s in shifts])
    lower = (X[model.rest.cells].mean(1)[:, 2] < 0.5).to(torch.float64)

    def forward(theta):
        return qs(torch.exp(theta[0] * lower), positions).reshape(-1)

    with counting() as count:                   # the synthetic data and the fit
        data = forward(torch.tensor([0.4], dtype=torch.float64)).detach()
        qs.clear_cache()
        result = levenberg_marquardt(ResidualFunction(forward, data),
                                     torch.zeros(1, dtype=torch.float64),
                                     LevenbergMarquardtConfig(max_iter=4))
    return result.theta, count


def test_a_four_frame_nonlinear_fit_makes_one_analysis():
    """The issue's count: every frame and Newton step of the body share one analysis (a
    plan per frame's slot made 24.7 s of the 998k-tetrahedron forward on the H200); the fit
    is SuperLU's to round-off."""
    fake = FakeCuda()
    theta, count = four_frame_fit(CudssBackend(runtime=fake))
    theta_cpu, count_cpu = four_frame_fit("scipy")
    assert count.analyses == 1 and fake.count("plan") == 1
    # the same solves; the factors that lost the one slot are factorised again (119 against
    # SuperLU's 91 when this was written): the price of one analysis and one factor's memory
    assert (count.solves, count.rhs_columns) == (count_cpu.solves, count_cpu.rhs_columns)
    assert count_cpu.factorizations <= count.factorizations <= count.solves
    assert float((theta - theta_cpu).abs().max()) < 1e-8
    assert abs(float(theta[0]) - 0.4) < 1e-3


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
    backend = CudssBackend(rhs_block=8)
    with counting() as c:
        factor = backend.factorize(pattern, values, True)
        x = factor.solve(rhs.cuda())                  # 11 columns: two blocks of 8
        x1 = factor.solve(rhs[:, 0].cuda())
    assert (c.analyses, c.factorizations, c.solves, c.rhs_columns) == (1, 1, 2, 12)
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
    dense = torch.from_numpy(pattern.to_scipy(indefinite).toarray())
    b = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    # (cuDSS reports a non-positive Cholesky pivot as info > 0: the fallback relies on it)
    with pytest.raises(SingularMatrixError, match="not positive definite"):
        CudssBackend(indefinite=False).factorize(pattern, indefinite, True).solve(b.cuda())
    # by default an indefinite symmetric matrix (a Newton tangent) is factorised as such
    factor = get_backend("cudss").factorize(pattern, indefinite, True)
    assert torch.allclose(factor.solve(b.cuda()).cpu(), torch.linalg.solve(dense, b),
                          rtol=1e-8, atol=1e-10)
    assert factor.info["kind"] == "symmetric"


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
        with counting() as count:
            x = qs(E, positions)
            (grad,) = torch.autograd.grad((x * x).sum(), E)   # autograd's CUDA thread
        results[device] = (x.detach().cpu(), grad.cpu(), count)
    assert float((results["cpu"][0] - results["cuda"][0]).abs().max()) < 1e-10
    assert torch.allclose(results["cpu"][1], results["cuda"][1], rtol=1e-8, atol=1e-10)
    # every frame and Newton step: one analysis; the same solves as on the CPU
    count, count_cpu = results["cuda"][2], results["cpu"][2]
    assert count.analyses == 1 and count.solves == count_cpu.solves


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
