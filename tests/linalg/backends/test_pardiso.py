"""The MKL PARDISO backend: accuracy, counters, the analysis kept per pattern, many live
factors, singular matrices, agreement with SuperLU inside the equilibrium solve."""
from __future__ import annotations

import gc

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfit.linalg import (PardisoUnavailableError, SingularMatrixError, SparsePattern,
                             counting, default_backend, get_backend, pardiso_available)
from torchfit.physics import Equilibrium

from helpers.linear_system import MatrixModel


def _requires_pardiso() -> None:
    pytest.importorskip("pypardiso")
    if not pardiso_available():
        pytest.skip("pypardiso is installed but MKL could not be loaded")


@pytest.fixture(scope="module")
def backend():
    _requires_pardiso()
    return get_backend("pardiso")


def pattern_of(matrix: sp.spmatrix) -> tuple[SparsePattern, torch.Tensor]:
    coo = matrix.tocoo()
    pattern = SparsePattern(coo.row, coo.col, coo.shape)
    return pattern, pattern.assemble(torch.from_numpy(coo.data.astype(np.float64)))


def matrices(n: int = 300, seed: int = 0) -> dict[str, sp.spmatrix]:
    """SPD, symmetric indefinite and nonsymmetric sparse matrices, well conditioned."""
    g = np.random.default_rng(seed)
    B = sp.random(n, n, density=4.0 / n, random_state=g)
    S = (B + B.T).tocsr()
    spd = S + sp.diags(np.abs(S).sum(axis=1).A1 + 1.0)        # diagonally dominant
    signs = np.where(np.arange(n) % 3 == 0, -1.0, 1.0)         # a third negative
    indefinite = S + sp.diags(signs * (np.abs(S).sum(axis=1).A1 + 1.0))
    nonsymmetric = B + sp.diags(np.abs(B).sum(axis=1).A1 + np.abs(B).sum(axis=0).A1 + 1.0)
    return {"spd": spd, "indefinite": indefinite, "nonsymmetric": nonsymmetric}


def relative_residual(A: np.ndarray, x: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(A @ x - b) / np.linalg.norm(b))


@pytest.mark.parametrize("kind", ["spd", "indefinite", "nonsymmetric"])
def test_solves_every_matrix_type_with_many_columns_and_transposed(backend, kind):
    matrix = matrices()[kind]
    symmetric = kind != "nonsymmetric"
    pattern, values = pattern_of(matrix)
    dense = pattern.to_scipy(values).toarray()
    if kind == "indefinite":
        assert np.linalg.eigvalsh(dense).min() < 0 < np.linalg.eigvalsh(dense).max()
    g = torch.Generator().manual_seed(1)
    rhs = torch.randn(pattern.shape[0], 5, dtype=torch.float64, generator=g)
    with counting() as count:
        factor = backend.factorize(pattern, values, symmetric)
        x = factor.solve(rhs)
        x1 = factor.solve(rhs[:, 0])
        xt = factor.solve(rhs, transpose=True)
    # a new pattern: its analysis (ordering, symbolic factorisation) is counted too
    assert count.as_dict() == {"factorizations": 1, "solves": 3, "rhs_columns": 11,
                               "analyses": 1}
    assert x.shape == rhs.shape and x1.shape == (pattern.shape[0],) and x.dtype == torch.float64
    b = rhs.numpy()
    assert relative_residual(dense, x.numpy(), b) < 1e-12
    assert relative_residual(dense, x1.numpy(), b[:, 0]) < 1e-12
    assert relative_residual(dense.T, xt.numpy(), b) < 1e-12
    if kind == "nonsymmetric":              # the transpose is really another system
        assert not np.allclose(x.numpy(), xt.numpy())
    reference = get_backend("scipy").factorize(pattern, values, symmetric).solve(rhs)
    assert torch.allclose(x, reference, rtol=0, atol=1e-10)


def test_only_the_upper_triangle_is_read_for_symmetric_matrices(backend):
    """A symmetric matrix whose pattern stores some entries only below the diagonal (and
    some only above) gives the answer of the full matrix."""
    full = matrices(60)["spd"].tocoo()
    above, below = full.row < full.col, full.row > full.col
    keep = (full.row == full.col) | (above & (full.col % 3 != 0)) | (below & (full.row % 3 == 0))
    pattern = SparsePattern(full.row[keep], full.col[keep], full.shape)
    values = pattern.assemble(torch.from_numpy(full.data[keep]))
    assert pattern.nnz < full.nnz
    rhs = torch.randn(60, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    x = backend.factorize(pattern, values, True).solve(rhs)
    assert relative_residual(full.toarray(), x.numpy(), rhs.numpy()) < 1e-12


def test_analysis_is_made_once_per_pattern_and_shared_by_live_factors(backend):
    matrix = matrices(200, seed=3)["indefinite"]
    pattern, values = pattern_of(matrix)
    plan = backend.plan(pattern, True)
    assert plan.analyses == 0
    dense = pattern.to_scipy(values).toarray()
    scales = torch.linspace(0.5, 3.0, 48, dtype=torch.float64)
    rhs = torch.randn(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    with counting() as count:
        factors = [backend.factorize(pattern, s * values, True) for s in scales]   # 48 live
        solutions = [f.solve(rhs) for f in reversed(factors)][::-1]
    assert count.factorizations == 48 and count.solves == 48 and count.rhs_columns == 144
    assert plan.analyses == 1 and len(plan.handles) == 1 and count.analyses == 1
    for s, x in zip(scales.tolist(), solutions):             # every factor its own matrix
        assert relative_residual(s * dense, x.numpy(), rhs.numpy()) < 1e-12
    handle = plan.handles[0]
    assert handle.free_slots == handle.capacity - 48
    # a factor that is garbage collected gives its slot (and memory) back; the analysis
    # stays with the pattern for the next factorisations, also through a new backend
    del factors, solutions
    gc.collect()
    assert handle.free_slots == handle.capacity
    with counting() as count:
        again = get_backend("pardiso").factorize(pattern, values, True)
    assert plan.analyses == 1 and count.analyses == 0
    assert relative_residual(dense, again.solve(rhs).numpy(), rhs.numpy()) < 1e-12
    # an equilibrium without Dirichlet dofs (the same free pattern) makes a backend of its
    # own: still no new analysis
    model = MatrixModel(pattern, values, rhs.T)
    eq = Equilibrium(model, torch.tensor([], dtype=torch.long), backend="pardiso",
                     allow_no_dirichlet=True)
    assert eq.free_pattern.nnz == pattern.nnz
    x = eq(torch.zeros(pattern.shape[0], dtype=torch.float64), torch.zeros(3, 0)).T
    assert plan.analyses == 1 and relative_residual(dense, x.numpy(), rhs.numpy()) < 1e-12


def test_a_full_handle_opens_a_second_analysis(backend):
    from torchfit.linalg import PardisoBackend
    small = PardisoBackend(capacity=3)
    pattern, values = pattern_of(matrices(50, seed=5)["spd"])
    factors = [small.factorize(pattern, (1 + i) * values, True) for i in range(5)]
    plan = small.plan(pattern, True)
    assert plan.analyses == 2 and [h.capacity for h in plan.handles] == [3, 3]
    rhs = torch.ones(50, dtype=torch.float64)
    dense = pattern.to_scipy(values).toarray()
    for i, f in enumerate(factors):
        assert relative_residual((1 + i) * dense, f.solve(rhs).numpy(), rhs.numpy()) < 1e-12


def test_nonsymmetric_factors_have_their_own_analysis(backend):
    pattern, values = pattern_of(matrices(80, seed=6)["nonsymmetric"])
    factors = [backend.factorize(pattern, values * (1 + i), False) for i in range(3)]
    assert backend.plan(pattern, False).analyses == 3
    rhs = torch.ones(80, dtype=torch.float64)
    dense = pattern.to_scipy(values).toarray()
    for i, f in enumerate(factors):
        assert relative_residual((1 + i) * dense, f.solve(rhs).numpy(), rhs.numpy()) < 1e-12


@pytest.mark.parametrize("symmetric", [True, False])
def test_singular_matrices_raise(backend, symmetric):
    pattern = SparsePattern([0, 0, 1, 1], [0, 1, 0, 1], (2, 2))
    values = pattern.assemble(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    with pytest.raises(SingularMatrixError, match="singular"):
        backend.factorize(pattern, values, symmetric)
    eq = Equilibrium(MatrixModel(pattern, values, torch.ones(1, 2), symmetric=symmetric),
                     torch.tensor([], dtype=torch.long), backend="pardiso",
                     allow_no_dirichlet=True)
    with pytest.raises(SingularMatrixError, match="singular"):
        eq(torch.zeros(2, dtype=torch.float64), torch.zeros(1, 0))
    # an empty row (no entry at all) is a zero pivot, not a crash
    empty = SparsePattern([0, 2], [0, 2], (3, 3))
    with pytest.raises(SingularMatrixError):
        backend.factorize(empty, torch.ones(2, dtype=torch.float64), symmetric)
    with pytest.raises(SingularMatrixError, match="NaN"):
        backend.factorize(pattern, torch.tensor([1.0, float("nan"), 0.0, 1.0],
                                                dtype=torch.float64), symmetric)


def test_free_floating_elastic_body_is_singular(backend):
    from torchfit.mesh import box_tetrahedra
    from torchfit.physics.elasticity import SimplicialElasticity
    mesh = box_tetrahedra(2, 2, 2)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "linear", nu=0.3)
    rest = model.rest.points.reshape(1, -1)
    values = model.tangent_pattern.assemble(model.tangent_values(
        rest, torch.ones(model.n_cells, dtype=torch.float64)))[0]
    with pytest.raises(SingularMatrixError, match="Dirichlet"):
        backend.factorize(model.tangent_pattern, values, True)


def test_float32_values_give_float32_solutions(backend):
    pattern, values = pattern_of(matrices(40, seed=7)["spd"])
    x = backend.factorize(pattern, values.float(), True).solve(torch.ones(40))
    assert x.dtype == torch.float32
    assert relative_residual(pattern.to_scipy(values).toarray(), x.double().numpy(),
                             np.ones(40)) < 1e-6


@pytest.mark.parametrize("material", ["linear", "corotated"])
def test_equilibrium_agrees_with_superlu_forward_backward_and_jvp(backend, material):
    from helpers.tetbox import forward_backward_jvp, twisted_box

    results = {name: forward_backward_jvp(*twisted_box(material, name))
               for name in ("scipy", "pardiso")}
    x_s, grad_s, tan_s, count_s = results["scipy"]
    x_p, grad_p, tan_p, count_p = results["pardiso"]
    assert float((x_p - x_s).abs().max()) < 1e-11
    assert float((grad_p - grad_s).norm() / grad_s.norm()) < 1e-9
    assert float((tan_p - tan_s).norm() / tan_s.norm()) < 1e-9
    # the same factorisations and solves, counted alike; PARDISO analyses the pattern once
    # for the forward (Newton), the adjoint and the jvp, SuperLU counts none of its own
    assert count_p.pop("analyses") == 1 and count_s.pop("analyses") == 0
    assert count_p == count_s


def test_default_backend_is_pardiso_for_3d_cpu_problems_only(backend):
    assert default_backend(3, "cpu") == "pardiso"
    assert default_backend(2, "cpu") == "scipy"
    assert default_backend(3, torch.device("meta")) == "cg"     # off the CPU: the any-device CG


def test_missing_extra_is_one_line_naming_it(monkeypatch):
    import sys

    from torchfit.linalg.backends import pardiso_mkl as binding
    monkeypatch.setattr(binding, "_LIBRARY", None)
    monkeypatch.setattr(binding, "_LIBRARY_ERROR", None)
    monkeypatch.setitem(sys.modules, "pypardiso", None)      # import fails
    with pytest.raises(PardisoUnavailableError) as info:
        get_backend("pardiso")
    message = str(info.value)
    assert "\n" not in message and "pip install 'torchfit[pardiso]'" in message
    assert "x86-64" in message and isinstance(info.value, ImportError)
    assert not pardiso_available() and default_backend(3) == "scipy"


def test_thread_limit_of_set_threads_reaches_mkl(backend):
    from threadpoolctl import threadpool_info, threadpool_limits

    from torchfit.linalg import set_threads
    from torchfit.linalg import threads as thread_module

    def mkl_threads() -> set[int]:
        return {int(i["num_threads"]) for i in threadpool_info() if i.get("internal_api") == "mkl"}

    if not mkl_threads():
        pytest.skip("threadpoolctl does not see MKL here")
    before_torch, before_requested = torch.get_num_threads(), thread_module.requested_threads()
    before = {i["filepath"]: i["num_threads"] for i in threadpool_info()}
    try:
        set_threads(1)
        assert mkl_threads() == {1}
    finally:
        for count in set(before.values()):
            threadpool_limits(limits=count)
        torch.set_num_threads(before_torch)
        thread_module._REQUESTED = before_requested


def _laplacian_3d(n: int) -> sp.csr_matrix:
    lap = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.identity(n)
    return (sp.kron(sp.kron(lap, eye), eye) + sp.kron(sp.kron(eye, lap), eye)
            + sp.kron(sp.kron(eye, eye), lap)).tocsr()


_LOWER_LIMIT_SCRIPT = """
import numpy as np, scipy.sparse as sp, torch
from threadpoolctl import threadpool_limits
from torchfit.linalg import SparsePattern, get_backend
n = 20
lap = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n)); eye = sp.identity(n)
A = (sp.kron(sp.kron(lap, eye), eye) + sp.kron(sp.kron(eye, lap), eye)
     + sp.kron(sp.kron(eye, eye), lap)).tocoo()
pattern = SparsePattern(A.row, A.col, A.shape)
values = pattern.assemble(torch.from_numpy(A.data))
backend = get_backend("pardiso")
threadpool_limits(limits=2)
first = backend.factorize(pattern, values, True)
threadpool_limits(limits=1)
second = backend.factorize(pattern, 2 * values, True)
b = np.ones(A.shape[0])
x = second.solve(torch.from_numpy(b)).numpy()
assert np.linalg.norm(2 * (A @ x) - b) < 1e-10 * np.linalg.norm(b)
print("factorised under a lower thread limit")
"""


def test_a_lower_thread_limit_than_the_analysis_had_does_not_crash_mkl(backend):
    """A problem built under two MKL threads and fitted under one (the app builds the
    problem before ``fit`` applies ``threads=1``): factorising into the handle analysed
    under two threads was a segmentation fault (8,000 unknowns; 1,000 did not crash).
    Run in a child process, so that a regression fails this test instead of killing
    the test session."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", _LOWER_LIMIT_SCRIPT], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, (result.returncode, result.stderr[-2000:])
    assert "factorised under a lower thread limit" in result.stdout


def test_a_changed_thread_limit_gets_its_own_analysis(backend):
    from threadpoolctl import threadpool_info, threadpool_limits

    if not any(i.get("internal_api") == "mkl" for i in threadpool_info()):
        pytest.skip("threadpoolctl does not see MKL here")
    pattern, values = pattern_of(_laplacian_3d(8))
    plan = backend.plan(pattern, True)
    before = {i["filepath"]: i["num_threads"] for i in threadpool_info()}
    rhs = torch.ones(pattern.shape[0], dtype=torch.float64)
    dense = pattern.to_scipy(values).toarray()
    try:
        threadpool_limits(limits=2)
        first = backend.factorize(pattern, values, True)
        backend.factorize(pattern, values, True)              # same limit: same analysis
        assert plan.analyses == 1
        threadpool_limits(limits=1)
        second = backend.factorize(pattern, 3 * values, True)
        assert plan.analyses == 2
        assert [h.threads for h in plan.handles] == [1]        # the old handle is dropped
        # the factor made under two threads still solves (its handle lives with it)
        assert relative_residual(dense, first.solve(rhs).numpy(), rhs.numpy()) < 1e-12
        assert relative_residual(3 * dense, second.solve(rhs).numpy(), rhs.numpy()) < 1e-12
    finally:
        for count in set(before.values()):
            threadpool_limits(limits=count)
