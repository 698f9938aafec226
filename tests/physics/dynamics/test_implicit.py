"""The implicit integrator (backward Euler, BDF2): derivatives (Taylor rate 2 +- 0.05, dot
product to 1e-10) with every state kept and checkpointed, on the chain and the corotated
sheet; its counted cost."""
from __future__ import annotations

import pytest
import torch

from torchfit.linalg.counters import counting
from torchfit.physics.dynamics import make_integrator

from helpers.dynamics_systems import (chain_system, check_derivatives,
                                      one_thread, residual_of, sheet_system)  # noqa: F401 (autouse)


@pytest.mark.parametrize("scheme,checkpoint_every", [("bdf2", 1), ("bdf2", 4),
                                                     ("backward_euler", 1)])
def test_implicit_derivatives_on_the_chain(scheme, checkpoint_every):
    system, params = chain_system()
    integrator = make_integrator("implicit", system, torch.linspace(0.05, 0.3, 6), dt=0.01,
                                 scheme=scheme, checkpoint_every=checkpoint_every)
    taylor, dot = check_derivatives(integrator, params)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    assert dot.rel_error <= 1e-10, dot.rel_error


def test_implicit_derivatives_on_the_corotated_sheet():
    system, params = sheet_system()
    integrator = make_integrator("implicit", system, torch.tensor([0.1, 0.2]), dt=0.04,
                                 checkpoint_every=2)
    taylor, dot = check_derivatives(integrator, params)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    assert dot.rel_error <= 1e-10, dot.rel_error


def test_cost_is_counted_and_stored_solutions_make_products_solve_only():
    system, params = chain_system(n=6)
    times = torch.linspace(0.05, 0.3, 6)
    integrator = make_integrator("implicit", system, times, dt=0.01)
    steps = integrator.n_steps
    with counting() as forward:
        integrator(params)
    assert forward.factorizations == steps            # linear springs: one per step
    assert forward.solves == steps
    residual, theta = residual_of(integrator, params)
    lin = residual.linearize(theta)
    with counting() as products:
        lin.vjp(lin.r)
        lin.jvp(theta)
    assert products.factorizations == 0               # every step's factor is kept (c = 1)
    assert products.solves == 2 * steps
    checkpointed = make_integrator("implicit", system, times, dt=0.01, checkpoint_every=5)
    assert checkpointed.stored_states < integrator.stored_states == steps + 1
    lin = residual_of(checkpointed, params)[0].linearize(theta)
    with counting() as products:
        lin.vjp(lin.r)
    # every segment recomputed from its checkpoint (one factorisation per step), then one
    # factorisation per step replayed, except the segment's last two (still cached)
    assert products.factorizations == 2 * steps - 2 * len(checkpointed.segments())
