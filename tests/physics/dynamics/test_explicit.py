"""The torchdiffeq integrator: derivatives (dopri5 at a tight tolerance, rk4 on the sheet),
a blow-up that names the implicit integrator, and a trial's budget of right-hand sides."""
from __future__ import annotations

import math

import pytest
import torch

from torchfit.physics.dynamics import UnstableStepError, make_integrator
from torchfit.physics.dynamics.explicit import fastest_rate
from torchfit.physics.equilibrium import TrialBudgetExceeded

from helpers.dynamics_systems import (chain_system, check_derivatives, one_line,
                                      sheet_system)


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


def _budgeted(factor: float):
    system, params = chain_system(n=4, stiffness=10.0)
    integrator = make_integrator("torchdiffeq", system, torch.linspace(0.1, 1.0, 5), dt=0.01,
                                 method="dopri5", rtol=1e-8, atol=1e-10, trial_factor=factor)
    return integrator, params


def test_a_stiff_trial_stops_at_its_budget_of_right_hand_sides():
    """A trial whose stiffness damping overdamps the stiffest mode (beta x 1e4: the fast
    rate beta omega_max^2 sets dopri5's step) is cut at trial_factor x the anchor's
    right-hand sides, not integrated to the end; the anchor's own parameters, and any point
    before derivatives were taken, have no limit."""
    integrator, params = _budgeted(3.0)
    stiff = params.clone()
    stiff[-1] = 20.0
    assert integrator.trial_budget(stiff) is None          # no anchor yet
    integrator.jacobian(params, torch.eye(params.numel(), dtype=params.dtype)[:, :1])
    anchor = integrator.solve(params).evaluations
    assert anchor > 50
    assert integrator.trial_budget(params) is None
    assert integrator.trial_budget(stiff) == math.ceil(3.0 * anchor)
    before = integrator.evaluations
    with pytest.raises(TrialBudgetExceeded) as info:
        integrator(stiff)
    spent = integrator.evaluations - before
    assert spent == math.ceil(3.0 * anchor), (spent, anchor)
    text = one_line(info.value)
    assert "trial budget" in text and "overdamped by beta = 20" in text, text
    # without a budget the same trial costs many times more
    free = make_integrator("torchdiffeq", integrator.system, integrator.output_times, dt=0.01,
                           method="dopri5", rtol=1e-8, atol=1e-10)
    free(stiff)
    assert free.evaluations > 10 * anchor, (free.evaluations, anchor)


def test_an_accepted_trial_differentiates_beyond_the_budget_of_its_forward_pass():
    """The budget limits the trial's forward integration only: its continuous adjoint
    (through the same right-hand side, backward in time) runs unlimited, and the gradient
    is the unbudgeted integrator's."""
    integrator, params = _budgeted(1.2)
    integrator.jacobian(params, torch.eye(params.numel(), dtype=params.dtype)[:, :1])
    trial = (params * (1.0 + 1e-3)).requires_grad_(True)
    budget, start = integrator.trial_budget(trial.detach()), integrator.evaluations
    x = integrator(trial)
    assert integrator.evaluations - start <= budget
    (grad,) = torch.autograd.grad(x.square().sum(), trial)
    assert integrator.evaluations - start > budget       # the adjoint went past it
    free, _ = _budgeted(0.0)
    trial_free = trial.detach().requires_grad_(True)
    (grad_free,) = torch.autograd.grad(free(trial_free).square().sum(), trial_free)
    assert torch.equal(grad, grad_free)


def test_the_fast_rate_of_an_overdamped_mode():
    """An underdamped stiffest mode oscillates at omega_max; an overdamped one decays at
    the fast root of lambda^2 + (alpha + beta omega^2) lambda + omega^2, about the damping
    rate alpha + beta omega^2 (less omega^2 over it) once that is large."""
    assert fastest_rate(100.0, 0.5, 1e-3) == 100.0
    damping = 0.5 + 0.05 * 100.0 ** 2
    rate = fastest_rate(100.0, 0.5, 0.05)
    assert abs(rate ** 2 - damping * rate + 100.0 ** 2) <= 1e-9 * damping ** 2
    assert damping - 2 * 100.0 ** 2 / damping <= rate <= damping
