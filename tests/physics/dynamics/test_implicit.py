"""The implicit integrator (backward Euler, BDF2): derivatives (Taylor rate 2 +- 0.05, dot
product to 1e-10) with every state kept and checkpointed, on the chain and the corotated
sheet; its counted cost."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfit.linalg.counters import counting
from torchfit.mesh import rectangle_triangles
from torchfit.physics.dynamics import DynamicSystem, KeyedMotion, make_integrator
from torchfit.physics.elasticity import SimplicialElasticity
from torchfit.physics.equilibrium import NewtonConvergenceError

from helpers.dynamics_systems import (DT, chain_system, check_derivatives,
                                      residual_of, sheet_system)


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


@pytest.mark.parametrize("scheme", ["bdf2", "backward_euler"])
def test_error_estimate_by_step_halving_predicts_the_true_error(scheme):
    """Richardson's estimate (difference to the half step times 2^p / (2^p - 1)) against the
    error to a reference 64 times finer: within a factor 1.5 for both schemes (it would be
    off by 4/3 or 2 with the wrong order), and it shrinks as h^p."""
    system, params = chain_system()
    times = torch.linspace(0.05, 0.3, 6)
    reference = make_integrator("implicit", system, times, dt=0.02 / 64, scheme=scheme)(params)
    estimates = []
    for dt in (0.025, 0.0125):         # 2 and 4 steps per output interval of 0.05 s
        integrator = make_integrator("implicit", system, times, dt=dt, scheme=scheme)
        report = integrator.error_estimate(params)
        true_error = float((integrator(params) - reference).abs().max())
        assert report["steps"] == integrator.n_steps
        assert report["reference_steps"] == 2 * integrator.n_steps
        assert true_error / 1.5 <= report["estimate"] <= 1.5 * true_error, (report, true_error)
        estimates.append(report["estimate"])
    order = 2 if scheme == "bdf2" else 1
    assert estimates[0] / estimates[1] == pytest.approx(2 ** order, rel=0.25)


@pytest.mark.parametrize("checkpoint_every", [1, 4])
def test_density_scale_derivatives_and_its_reductions(checkpoint_every):
    """A density scale ``s`` among the parameters (mass ``s M``: inertia, mass damping and
    weight): Taylor rate 2 and the dot test with it; ``s = 1`` is the unscaled system to
    round-off; without loads, ``s`` and the field both doubled is the same motion (every term
    of the step residual doubles), so the scale is what the data see of the density."""
    from torchfit.physics.dynamics import KeyedMotion

    times = torch.linspace(0.05, 0.3, 6)
    system, params = chain_system(density_scale=1.3)
    integrator = make_integrator("implicit", system, times, dt=0.01,
                                 checkpoint_every=checkpoint_every)
    taylor, dot = check_derivatives(integrator, params)
    assert abs(taylor.rate - 2.0) <= 0.05, taylor.rate
    assert dot.rel_error <= 1e-10, dot.rel_error
    # the scale's own column is not zero: the data see it
    column = integrator.jacobian(params, torch.eye(len(params), dtype=params.dtype)[:, -1:])
    assert float(column.abs().max()) > 1e-3
    plain_system, plain = chain_system()
    unit = torch.cat([plain, torch.ones(1, dtype=plain.dtype)])
    x_plain = make_integrator("implicit", plain_system, times, dt=0.01)(plain)
    assert float((integrator(unit) - x_plain).abs().max()) <= 1e-12
    n = system.n_field
    quiet = KeyedMotion(torch.zeros(1, dtype=params.dtype),
                        torch.zeros(1, n + 1, dtype=params.dtype))
    still, base = chain_system(loads=quiet, density_scale=1.0)
    doubled = base.clone()
    doubled[:n] *= 2.0
    doubled[-1] = 2.0
    still_integrator = make_integrator("implicit", still, times, dt=0.01)
    x_base, x_doubled = still_integrator(base), still_integrator(doubled)
    assert float((x_base - still.x0).abs().max()) > 1e-2               # it falls
    assert float((x_doubled - x_base).abs().max()) <= 1e-10
    with pytest.raises(Exception, match="density scale = -1 must be positive"):
        still_integrator(torch.cat([base[:-1], torch.tensor([-1.0], dtype=base.dtype)]))


def test_static_equilibrium_balances_the_external_force():
    """At rest under gravity and loads at t0: the elastic force balances them on the free
    dofs, the prescribed dof at its position; no inertia, no damping."""
    system, params = chain_system()
    integrator = make_integrator("implicit", system, torch.tensor([0.1]), dt=0.01)
    x = integrator.static_equilibrium(params, system.x0)
    field = system.split(params)[0]
    residual = system.elastic.residual(x[None], field)[0] - system.external_force(
        integrator.step_times[:1].to(x))[0]
    free = system.free_dofs
    assert float(residual[free].abs().max()) <= 1e-9 * float(system.external_force(
        integrator.step_times[:1].to(x)).abs().max())
    assert float(x[system.fixed_dofs].abs().max()) == 0.0       # the chain's top stays put
    assert float((x - system.x0).abs().max()) > 1e-3              # it hangs lower than rest

def hanging_strip(youngs_modulus: float):
    """A corotated 1 m x 0.1 m strip (8 x 2 cells, unit density) held at its left edge, under
    gravity across it: at 1000 Pa its linear tip deflection would be 1.5 m; it hangs."""
    mesh = rectangle_triangles(8, 2, 1.0, 0.1)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "corotated", nu=0.3)
    left = mesh.boundary_vertices("left")
    fixed = torch.as_tensor((left[:, None] * 2 + np.arange(2)).reshape(-1))
    rest = model.rest.points.to(DT)
    mass = torch.zeros(model.n_vertices, dtype=DT).index_add(
        0, torch.as_tensor(mesh.cells.reshape(-1)),
        (model.rest.volumes.to(DT) / 3.0).repeat_interleave(3)).repeat_interleave(2)
    gravity = torch.tensor([0.0, -9.81], dtype=DT).repeat(model.n_vertices)
    held = KeyedMotion(torch.zeros(1, dtype=DT), rest[torch.as_tensor(left)].reshape(1, -1))
    system = DynamicSystem(model, model.n_cells, mass, fixed, held, None, gravity,
                           rest.reshape(-1), vertex_dim=2)
    params = torch.cat([torch.full((model.n_cells,), youngs_modulus, dtype=DT),
                        torch.zeros(2, dtype=DT)])
    return system, params


def test_a_large_sag_is_found_by_load_increments():
    """Newton from the rest shape cannot take the strip's whole weight at once (its residual
    stalls); in increments it reaches the hanging equilibrium, balanced to the whole load's
    tolerance. With no room to cut the increment the failure is raised."""
    system, params = hanging_strip(1000.0)
    t0 = torch.zeros(1, dtype=DT)
    zeros = torch.zeros(system.n_dofs, dtype=DT)
    integrator = make_integrator("implicit", system, torch.tensor([0.1]), dt=0.05)
    with pytest.raises(NewtonConvergenceError):                  # the whole weight at once
        integrator.equilibrium(integrator.model.pack(params, zeros, zeros, zeros, 0.0, 0.0),
                               system.fixed_positions(t0), system.x0[None])
    x = integrator.static_equilibrium(params, system.x0)
    assert integrator.static_increments > 1
    weight = system.external_force(t0)[0]
    residual = system.elastic.residual(x[None], system.split(params)[0])[0] - weight
    free = system.free_dofs
    assert float(residual[free].norm()) <= 1e-9 * float(weight[free].norm())
    assert float(x.reshape(-1, 2)[:, 1].min()) < -0.3                # the tip hangs 0.37 m low
    assert torch.equal(x[system.fixed_dofs], system.x0[system.fixed_dofs])
    with pytest.raises(NewtonConvergenceError):
        make_integrator("implicit", system, torch.tensor([0.1]), dt=0.05).static_equilibrium(
            params, system.x0, min_fraction=0.25)
