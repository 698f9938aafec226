"""The backends behind one ``Factor`` interface: SuperLU and Jacobi-CG solves against
scipy, their errors (singular and nonsymmetric matrices, unknown names)."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfit.linalg import CGBackend, SingularMatrixError, SparsePattern, get_backend
from torchfit.physics import Equilibrium

from helpers.linear_system import MatrixModel, chain_pattern


def test_solution_matches_scipy_spsolve():
    pattern, values_of = chain_pattern(30)
    values = values_of(torch.rand(29) + 1)
    b = torch.randn(30)
    ref = sp.linalg.spsolve(pattern.to_scipy(values).tocsc(), b.numpy())
    for backend in ("scipy", "cg"):
        factor = get_backend(backend).factorize(pattern, values, True)
        for transpose in (False, True):
            x = factor.solve(b, transpose=transpose)
            assert np.allclose(x.numpy(), ref, rtol=1e-10, atol=1e-12)


def test_singular_matrix_is_reported():
    pattern = SparsePattern([0, 0, 1, 1], [0, 1, 0, 1], (2, 2))
    values = pattern.assemble(torch.tensor([1.0, -1.0, -1.0, 1.0]))
    with pytest.raises(SingularMatrixError, match="singular"):
        get_backend("scipy").factorize(pattern, values, True)
    # the same matrix as the tangent of a linear equilibrium without Dirichlet dofs
    model = MatrixModel(pattern, values, torch.zeros(1, 2))
    eq = Equilibrium(model, torch.tensor([], dtype=torch.long), allow_no_dirichlet=True)
    with pytest.raises(SingularMatrixError, match="singular"):
        eq(torch.zeros(2), torch.zeros(1, 0))


def test_unknown_backend_names_choices():
    with pytest.raises(ValueError, match="scipy"):
        get_backend("cholmod-please")


def test_cg_backend_refuses_nonsymmetric():
    pattern, values_of = chain_pattern(4)
    with pytest.raises(ValueError, match="symmetric"):
        CGBackend().factorize(pattern, values_of(torch.ones(3)), symmetric=False)
