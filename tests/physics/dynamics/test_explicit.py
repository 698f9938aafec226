"""The torchdiffeq integrator: derivatives (dopri5 at a tight tolerance, rk4 on the sheet)
and a blow-up that names the implicit integrator."""
from __future__ import annotations

import pytest
import torch

from torchfit.physics.dynamics import UnstableStepError, make_integrator

from helpers.dynamics_systems import (chain_system, check_derivatives, one_line,
                                      one_thread, sheet_system)  # noqa: F401 (autouse)


def test_torchdiffeq_derivatives_dopri5_tight_tolerance():
    system, params = chain_system(n=4, stiffness=10.0)
    integrator = make_integrator("torchdiffeq", system, torch.linspace(0.05, 0.2, 4), dt=0.01,
                                 method="dopri5", rtol=1e-13, atol=1e-14)
    taylor, dot = check_derivatives(integrator, params, taylor_steps=14)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    assert dot.rel_error <= 1e-10, dot.rel_error


def test_torchdiffeq_derivatives_rk4_and_the_sheet():
    system, params = sheet_system("linear")
    integrator = make_integrator("torchdiffeq", system, torch.tensor([0.05, 0.1]), dt=0.002,
                                 method="rk4")
    taylor, dot = check_derivatives(integrator, params, taylor_steps=14)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    # the continuous adjoint against the exact derivative of rk4's discrete map
    assert dot.rel_error <= 1e-6, dot.rel_error


def test_explicit_blow_up_names_the_implicit_integrator():
    system, params = chain_system(n=6, stiffness=100.0)
    integrator = make_integrator("torchdiffeq", system, torch.linspace(0.1, 2.0, 20), dt=0.1,
                                 method="rk4")
    with pytest.raises(UnstableStepError) as info:
        integrator(params)
    text = one_line(info.value)
    assert "blew up" in text and "problem.integrator=implicit" in text and "omega_max" in text
    # the implicit integrator takes the same step
    x = make_integrator("implicit", system, torch.linspace(0.1, 2.0, 20), dt=0.1)(params)
    assert bool(torch.isfinite(x).all())


def test_dense_jacobian_is_one_augmented_solve_equal_to_the_columns_one_by_one(monkeypatch):
    """All k tangent columns ride one odeint call, each right-hand side forming them in two
    reverse passes whatever k (the code before took 1 + k passes, one per column: the
    792 s first LM iteration of the 66-parameter chain); the columns equal those
    integrated one at a time to the ODE tolerance."""
    system, params = chain_system(n=4, stiffness=10.0)
    integrator = make_integrator("torchdiffeq", system, torch.linspace(0.05, 0.2, 4), dt=0.01,
                                 method="dopri5", rtol=1e-10, atol=1e-12)
    V = torch.randn(params.numel(), 3, generator=torch.Generator().manual_seed(0),
                    dtype=params.dtype) * params[:, None]
    integrator.solve(params)
    grad, calls = torch.autograd.grad, [0]

    def counted(*args, **kwargs):
        calls[0] += 1
        return grad(*args, **kwargs)

    monkeypatch.setattr(torch.autograd, "grad", counted)
    before = integrator.evaluations
    together = integrator.jacobian(params, V)
    evaluations = integrator.evaluations - before
    monkeypatch.setattr(torch.autograd, "grad", grad)
    assert calls[0] == 2 * evaluations, (calls[0], evaluations)
    alone = torch.cat([integrator.jacobian(params, V[:, j:j + 1]) for j in range(3)], dim=2)
    scale = float(alone.abs().max())
    assert together.shape == alone.shape == (4, system.n_dofs, 3)
    assert float((together - alone).abs().max()) <= 1e-7 * scale
