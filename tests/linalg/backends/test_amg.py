"""The ``amg`` backend (pyamg smoothed aggregation + CG): agreement with the direct
solvers, one hierarchy per factorisation reused by every solve, the rigid-body
near-nullspace, the direct fallback for matrices CG must not take, gradients of an
elastic box, and the automatic choice above the size threshold."""
from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("pyamg")

from torchfit.linalg import (AmgBackend, ScipyBackend, SingularMatrixError, counting,  # noqa: E402
                             default_backend, get_backend)
from torchfit.linalg.backends import choice as backends_module  # noqa: E402
from torchfit.linalg.backends.amg import HIERARCHY, translation_modes  # noqa: E402
from torchfit.problems.config import Backend, resolve_backend  # noqa: E402

from helpers.grid_matrices import grid_laplacian  # noqa: E402
from helpers.tetbox import clamped_box, forward_backward_jvp, twisted_box  # noqa: E402


def multilevel(backend):
    """``backend`` with a coarsest level of at most 10 unknowns (the default, 500, would
    leave these small test matrices on one level, solved exactly)."""
    backend.hierarchy_options = {**HIERARCHY, "max_coarse": 10}
    return backend


def box_stiffness(backend: str = "scipy"):
    """The reduced linear-elastic stiffness of a small clamped box (36 free nodes)."""
    model, qs, _, _ = clamped_box((3, 3, 5), (0.6, 0.6, 1.0), "linear", backend)
    E = torch.exp(0.5 * torch.randn(model.n_cells, dtype=torch.float64,
                                    generator=torch.Generator().manual_seed(3)))
    eq = qs.equilibrium
    if backend == "amg":
        multilevel(eq.backend)
    values = eq.reduction.free_values(model.tangent_values(model.rest.points.reshape(1, -1),
                                                           E))[0]
    return model, qs, eq, values


def test_amg_solves_match_superlu_and_count_one_factorisation_k_solves():
    model, qs, eq, values = box_stiffness("amg")
    pattern = eq.free_pattern
    rhs = torch.randn(pattern.shape[0], 4, dtype=torch.float64,
                      generator=torch.Generator().manual_seed(1))
    backend = eq.backend
    assert isinstance(backend, AmgBackend)
    with counting() as count:
        factor = backend.factorize(pattern, values, True)
        x = factor.solve(rhs)                          # a block of 4 columns
        x1 = factor.solve(rhs[:, 0], transpose=True)   # the adjoint: the same solve
        x2 = factor.solve(rhs[:, 1])
    assert count.as_dict() == {"factorizations": 1, "solves": 3, "rhs_columns": 6,
                               "analyses": 0}
    assert type(factor).__name__ == "AmgFactor" and backend.fallbacks == 0
    ref = ScipyBackend().factorize(pattern, values, True).solve(rhs)
    assert float((x - ref).norm() / ref.norm()) < 1e-9
    assert float((x1 - ref[:, 0]).norm() / ref[:, 0].norm()) < 1e-9
    assert float((x2 - ref[:, 1]).norm() / ref[:, 1].norm()) < 1e-9
    residual = pattern.matvec(values, x.T).T - rhs
    assert float(residual.norm(dim=0).max() / rhs.norm(dim=0).min()) < 1e-9


def test_rigid_body_modes_are_registered_and_cut_the_iterations():
    """The equilibrium hands the 6 rigid modes of the free dofs to the backend; a
    backend that only sees the pattern finds its 3x3 blocks and uses 3 translations."""
    model, qs, eq, values = box_stiffness("amg")
    pattern = eq.free_pattern
    modes = eq.backend.near_nullspace(pattern)
    assert modes.shape == (pattern.shape[0], 6)
    # the 6 modes are rigid motions: the unreduced stiffness maps them to zero
    full = model.tangent_pattern.to_scipy(model.tangent_pattern.assemble(model.tangent_values(
        model.rest.points.reshape(1, -1), torch.ones(model.n_cells, dtype=torch.float64)))[0])
    rigid = model.near_nullspace().numpy()
    assert np.abs(full @ rigid).max() < 1e-10 * np.abs(full).max()
    plain = multilevel(get_backend("amg"))
    assert np.array_equal(plain.near_nullspace(pattern), translation_modes(pattern.shape[0], 3))
    rhs = torch.ones(pattern.shape[0], dtype=torch.float64)
    iterations = []
    for backend in (eq.backend, plain):
        factor = backend.factorize(pattern, values, True)
        factor.solve(rhs)
        iterations.append(factor.iterations)
    assert iterations[0] < iterations[1]
    # a scalar matrix (no 3x3 blocks) aggregates with the constant vector
    grid, grid_values = grid_laplacian(9, 7)
    assert plain.near_nullspace(grid).shape == (grid.shape[0], 1)


def test_indefinite_and_nonsymmetric_matrices_fall_back_to_the_direct_backend():
    pattern, values = grid_laplacian(10, 6, shift=-2.0)         # indefinite
    backend = multilevel(AmgBackend(fallback=ScipyBackend()))
    rhs = torch.randn(pattern.shape[0], dtype=torch.float64,
                      generator=torch.Generator().manual_seed(4))
    with counting() as count:
        factor = backend.factorize(pattern, values, True)
        x = factor.solve(rhs)
        x_again = factor.solve(rhs)                  # the direct factor is kept
    assert backend.fallbacks == 1
    assert count.factorizations in (1, 2) and count.solves == 2
    assert torch.allclose(pattern.matvec(values, x), rhs, atol=1e-9)
    assert torch.equal(x, x_again)
    # nonsymmetric: straight to the direct backend, one factorisation
    with counting() as count:
        factor = backend.factorize(pattern, values, symmetric=False)
    assert type(factor).__name__ == "ScipyFactor" and count.factorizations == 1
    # CG that cannot converge in max_iter: the same fallback, inside the solve
    spd_pattern, spd_values = grid_laplacian(10, 6)
    stalled = multilevel(AmgBackend(fallback=ScipyBackend(), max_iter=1, rtol=1e-14))
    with counting() as count:
        factor = stalled.factorize(spd_pattern, spd_values, True)
        x = factor.solve(rhs)
    assert stalled.fallbacks == 1 and count.factorizations == 2 and count.solves == 1
    assert type(factor.direct).__name__ == "ScipyFactor"
    assert torch.allclose(spd_pattern.matvec(spd_values, x), rhs, atol=1e-9)
    with pytest.raises(SingularMatrixError, match="NaN"):
        backend.factorize(spd_pattern, torch.full_like(spd_values, float("nan")), True)


def test_negative_curvature_in_cg_falls_back_inside_the_solve():
    """A symmetric matrix with a positive diagonal but indefinite: the hierarchy is built,
    CG meets p^T A p <= 0, and the solve is made by the direct backend."""
    pattern, values = grid_laplacian(8, 8)
    # shifted by half its smallest diagonal entry: indefinite, the diagonal stays positive
    on_diagonal = (pattern.row_indices == pattern.col_indices).to(values)
    shifted = values - 0.5 * float(pattern.diagonal(values).min()) * on_diagonal
    assert bool((pattern.diagonal(shifted) > 0).all())
    assert np.linalg.eigvalsh(pattern.to_scipy(shifted).toarray()).min() < 0
    backend = multilevel(AmgBackend(fallback=ScipyBackend()))
    rhs = torch.randn(pattern.shape[0], dtype=torch.float64,
                      generator=torch.Generator().manual_seed(5))
    factor = backend.factorize(pattern, shifted, True)
    x = factor.solve(rhs)
    assert backend.fallbacks == 1
    assert torch.allclose(pattern.matvec(shifted, x), rhs, atol=1e-8)


@pytest.mark.parametrize("material", ["linear", "corotated"])
def test_elastic_box_gradients_and_jvp_match_superlu(material):
    """Forward, adjoint gradient and jvp of the clamped box with backend=amg agree with
    SuperLU's to the CG tolerance; the same factorisations, and the same solves less the
    refinement step of the linear forward solve (skipped after an iterative solve);
    corotated: Newton with a hierarchy per tangent."""
    results = {}
    for name in ("scipy", "amg"):
        qs, positions = twisted_box(material, name)
        if name == "amg":
            multilevel(qs.equilibrium.backend)
        results[name] = forward_backward_jvp(qs, positions)
    (x_s, grad_s, tan_s, count_s), (x_a, grad_a, tan_a, count_a) = results.values()
    assert float((x_a - x_s).abs().max()) < 1e-10
    assert float((grad_a - grad_s).norm() / grad_s.norm()) < 1e-8
    assert float((tan_a - tan_s).norm() / tan_s.norm()) < 1e-8
    if material == "linear":
        assert count_a["factorizations"] == count_s["factorizations"] == 1
        assert count_a["solves"] == count_s["solves"] - 1
    else:                      # Newton: the same iterations, factorisations and solves
        assert count_a == count_s      # (no analyses counted: SuperLU and AMG keep none)


def test_auto_picks_amg_above_the_threshold_only(monkeypatch):
    from torchfit.linalg import pardiso_available

    direct = "pardiso" if pardiso_available() else "scipy"
    monkeypatch.setattr(backends_module, "AMG_MIN_DOFS", 1000)
    assert default_backend(3, "cpu", 1001) == "amg"
    assert default_backend(3, "cpu", 1000) == direct
    assert default_backend(3, "cpu") == direct                 # size unknown: unchanged
    assert default_backend(2, "cpu", 10**7) == "scipy"        # 2-D: unchanged
    assert default_backend(3, torch.device("meta"), 10**7) == "cg"
    # a Jacobian's many columns per factor keep the direct backend at any size
    monkeypatch.setattr(backends_module, "AMG_MAX_SOLVES", 4)
    assert default_backend(3, "cpu", 10**7, solves_per_factor=4) == "amg"
    assert default_backend(3, "cpu", 10**7, solves_per_factor=192) == direct
    assert resolve_backend(Backend.auto, torch.device("cpu"), 3, 5000, 192) == direct
    assert resolve_backend(Backend.auto, torch.device("cpu"), 3, 5000) == "amg"
    assert resolve_backend(Backend.auto, torch.device("cpu"), 3, 500) == direct
    assert resolve_backend(Backend.pardiso, torch.device("cpu"), 3, 5000) == "pardiso"
    # a QuasistaticElasticity built by name gets the backend object with its modes
    _, qs, _, _ = clamped_box((2, 2, 2), (1.0, 1.0, 1.0), "linear",
                              default_backend(3, "cpu", 1001))
    assert isinstance(qs.equilibrium.backend, AmgBackend)


def test_missing_pyamg_is_one_line_naming_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "pyamg", None)            # import fails
    from torchfit.linalg.backends.amg import AmgUnavailableError, amg_available

    assert not amg_available()
    with pytest.raises(AmgUnavailableError) as info:
        get_backend("amg")
    assert "\n" not in str(info.value) and "torchfit[amg]" in str(info.value)
    monkeypatch.setattr(backends_module, "AMG_MIN_DOFS", 10)
    assert default_backend(3, "cpu", 10**6) != "amg"


def test_problem_backend_amg_without_pyamg_is_refused_in_one_line(monkeypatch):
    from torchfit.problems import config as problem_config

    monkeypatch.setattr(problem_config, "amg_available", lambda: False)
    with pytest.raises(problem_config.ProblemConfigError) as info:
        problem_config.validate_config(problem_config.ProblemConfig(backend="amg"))
    message = str(info.value)
    assert "\n" not in message and "problem.backend" in message
    assert "torchfit[amg]" in message
    problem_config.validate_config(problem_config.ProblemConfig(backend="pardiso"
                                   if problem_config.pardiso_available() else "scipy"))
